"""The rasterization-free psi: each Gaussian's projected footprint, in-frustum and visibility
terms at a virtual camera, summed over an importance sample of Gaussians.

``w_i(T) = footprint_i(T) * inside_i(T) * visible_i(T)``: ``footprint_i = sqrt(det(J Sigma_i
J^T + 0.3 I))`` its projected area in pixels, ``inside_i`` a smooth (sigmoid) near-plane and
image-bounds test, ``visible_i`` the transmittance in front of the Gaussian through the map,
read from deep opacity maps (:mod:`agilegs.service.nbv.anchor.visibility`),
or, as a benchmark variant, an occlusion test from a point z-buffer of opaque Gaussians' means
(piecewise constant in the pose: no gradient, the ascent's line search sees it). The per-view
information of Gaussian i is modelled as proportional to ``w_i(T)``; how the model is fitted
to Hhat is in :mod:`agilegs.service.nbv.anchor.fitting`.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from agilegs.config.selection import POINT_ZBUFFER

from ..camera import Intrinsics
from ..gaussians import GaussianMap
from ..kernels import backend, gpu_proxy
from ..projection import covariance_3d
from ..rotations import quat_to_rotmat
from .visibility import OpacityMaps

__all__ = [
    "DIRECTION_KINDS",
    "ProxyPsi",
    "direction_factors",
    "local_axes",
    "pick_occluders",
    "to_camera",
]


def pick_occluders(
    gmap: GaussianMap,
    num: int,
    generator: torch.Generator | None,
    min_opacity: float = 0.05,
) -> Tensor | None:
    """Means [M, 3] of ``num`` opaque Gaussians (a seeded subset; all when fewer), or None."""
    if num <= 0:
        return None
    opaque = torch.nonzero(gmap.opacities.detach() >= min_opacity).squeeze(1)
    if opaque.numel() > num:
        pick = torch.randperm(opaque.numel(), generator=generator)[:num]
        opaque = opaque[pick.to(opaque.device)]
    return gmap.means.detach()[opaque]


@dataclass
class ProxyPsi:
    """The rasterization-free psi over a fixed importance sample of Gaussians.

    With the per-sample term ``w_s(T) = footprint_s(T) * inside_s(T) * visible_s(T)``:
    ``psi(T) = sum_s weight_s * log(1 + rate_s * w_s(T))`` when ``rate`` is set [S] (the fitted
    model, ``observation_rates``), ``psi(T) = sum_s weight_s * sum_q log(1 + rate_sq * w_s(T) *
    f_q(d_s(T)))`` when ``rate`` is per parameter slot [S, Q] (the directional model,
    ``directional_rates``: f_q the slot's direction factor, :func:`direction_factors`, of the
    ray d_s from the camera centre to the sample), else ``psi(T) = sum_s weight_s * w_s(T)``.
    ``visible_s``:
    with ``grid``, the transmittance from the camera centre to the sample through the
    map (deep opacity maps, differentiable in the pose); else, with ``occluders``, a point
    z-buffer test:
    the occluders' means (a seeded subset of the opaque Gaussians plus the samples
    themselves) are projected onto a ``occ_grid`` square grid; in each test (cover, tolerance)
    of ``occ_tests`` every occluder covers a square of ``cover`` cells and a sample passes when
    its depth is within ``tolerance`` (relative) of the nearest occluder over its cell; its
    visibility is the fraction of tests it passes (piecewise constant in the pose, no
    gradient: the ascent's line search sees it); with neither, 1.

    Attributes:
        means: sampled centres [S, 3].
        cov: their world covariances [S, 3, 3].
        weight: per-sample weight (c_i times the importance reweighting) [S].
        intrinsics: the virtual camera.
        near: soft near plane (world units).
        edge: sigmoid width of the image-bound test (pixels).
        occluders: occluder means [M, 3] (None: no occlusion test).
        occ_grid: z-buffer grid edge in cells.
        occ_tests: the visibility tests (cover in cells, odd; relative depth tolerance).
        rate: per-sample rate a_s of the log form [S], or per sample and parameter slot
            [S, Q] (the directional form), or None (the linear form).
        slot_kinds: the direction factor of each slot [Q] (indices into
            :func:`direction_factors`' last axis; the directional form only).
        axes: the samples' local axes, as columns [S, 3, 3] (the directional form only).
        grid: the occluders of the transmittance visibility (None: the z-buffer).
    """

    means: Tensor
    cov: Tensor
    weight: Tensor
    intrinsics: Intrinsics
    near: float
    edge: float
    occluders: Tensor | None = None
    occ_grid: int = 64
    rate: Tensor | None = None
    occ_tests: tuple[tuple[int, float], ...] = POINT_ZBUFFER
    grid: OpacityMaps | None = None
    slot_kinds: Tensor | None = None
    axes: Tensor | None = None

    @classmethod
    def build(
        cls,
        gmap: GaussianMap,
        c: Tensor,
        intrinsics: Intrinsics,
        *,
        num_samples: int,
        near: float,
        edge: float,
        generator: torch.Generator | None,
        num_occluders: int = 0,
        occ_grid: int = 64,
        occ_tests: tuple[tuple[int, float], ...] = POINT_ZBUFFER,
        min_opacity: float = 0.05,
        rate: Tensor | None = None,
        slots: int = 1,
        occluders: Tensor | None = None,
        grid: OpacityMaps | None = None,
        slot_kinds: Tensor | None = None,
    ) -> ProxyPsi:
        """Importance-sample ``num_samples`` Gaussians with probability ~ c [N] (seeded).

        Linear form (``rate`` None): ``psi = sum_i c_i w_i``, estimated by the sample.
        Log form (``rate`` [N]): ``psi = sum_i slots * log(1 + rate_i w_i)``, estimated by the
        sample drawn ~ c (c_i should be that Gaussian's typical term) and reweighted by
        ``1 / c_i``. Directional form (``rate`` [N, Q] with ``slot_kinds`` [Q]): ``psi =
        sum_i sum_q log(1 + rate_iq w_i f_q)``, sampled and reweighted alike (``slots`` is
        not used). ``num_samples`` 0 or >= N takes every Gaussian once, unweighted.
        ``grid`` gives the transmittance visibility; without it, ``num_occluders`` > 0
        enables the z-buffer test with that many opaque Gaussians (opacity >= ``min_opacity``;
        all of them when fewer) as occluders, or with ``occluders`` [M, 3] when given; 0
        disables it.
        """
        c = c.detach().clamp_min(0)
        n = c.shape[0]
        total = float(c.sum())
        directional = rate is not None and rate.ndim == 2
        if directional and slot_kinds is None:
            raise ValueError("a per-slot rate [N, Q] needs slot_kinds [Q]")
        per_slot = 1.0 if directional else float(slots)
        if num_samples == 0 or num_samples >= n or total <= 0:
            idx = torch.arange(n, device=c.device)
            w = c if rate is None else torch.full_like(c, per_slot)
        else:
            draws = torch.multinomial(
                c.cpu().double(), num_samples, replacement=True, generator=generator
            )
            uniq, counts = torch.unique(draws, return_counts=True)
            idx = uniq.to(c.device)
            w = counts.to(device=c.device, dtype=c.dtype) * (total / num_samples)
            if rate is not None:
                w = w * per_slot / c[idx].clamp_min(1e-30)
        means = gmap.means.detach()[idx]
        cov = covariance_3d(gmap.log_scales.detach()[idx], gmap.quats.detach()[idx])
        occ = (
            None if grid is not None else occluders
            if occluders is not None or num_occluders == 0
            else pick_occluders(gmap, num_occluders, generator, min_opacity)
        )
        return cls(
            means=means,
            cov=cov,
            weight=w,
            intrinsics=intrinsics,
            near=near,
            edge=edge,
            occluders=occ,
            occ_grid=occ_grid,
            rate=None if rate is None else rate.detach()[idx],
            occ_tests=tuple((int(c), float(t)) for c, t in occ_tests),
            grid=grid,
            slot_kinds=slot_kinds if directional else None,
            axes=local_axes(gmap.quats.detach()[idx]) if directional else None,
        )

    def visibility(
        self, c2w: Tensor, sample_cam: tuple[Tensor, Tensor, Tensor] | None = None
    ) -> Tensor:
        """The visibility of every sample from poses [B, 4, 4] -> [B, S]: the
        transmittance (with ``grid``, differentiable in the poses), else the z-buffer
        test's (:meth:`zbuffer_visibility`), else 1."""
        if self.grid is not None:
            return self.grid.transmittance(c2w, self.means, sample_cam)
        return self.zbuffer_visibility(c2w, sample_cam)

    @torch.no_grad()
    def zbuffer_visibility(
        self, c2w: Tensor, sample_cam: tuple[Tensor, Tensor, Tensor] | None = None
    ) -> Tensor:
        """The z-buffer visibility of every sample from poses [B, 4, 4] -> [B, S] (the
        fraction of ``occ_tests`` passed: 0 / 1 with one test; 1 without occluders).

        The samples occlude too. ``sample_cam``: the samples' camera coordinates (x, y, z),
        each [B, S], when the caller has them already.
        """
        b = c2w.shape[0]
        s = self.means.shape[0]
        dt = c2w.dtype
        if self.occluders is None:
            return torch.ones(b, s, dtype=dt, device=c2w.device)
        g = self.occ_grid
        k = self.intrinsics
        fx, fy = k.fx * g / k.width, k.fy * g / k.height
        cx, cy = k.cx * g / k.width, k.cy * g / k.height
        rot = c2w[:, :3, :3].detach()
        t = c2w[:, :3, 3].detach()
        if sample_cam is None:
            sample_cam = to_camera(self.means.to(dt), rot, t)
        ox, oy, oz = to_camera(self.occluders.to(dt), rot, t)
        x = torch.cat([ox, sample_cam[0].detach()], dim=1)
        y = torch.cat([oy, sample_cam[1].detach()], dim=1)
        z = torch.cat([oz, sample_cam[2].detach()], dim=1)
        iz = 1.0 / z.clamp_min(1e-9)
        u = x * iz * fx + cx
        v = y * iz * fy + cy
        ok = (z > self.near) & (u >= 0) & (u < g) & (v >= 0) & (v < g)
        cell = v.clamp(0, g - 1).long() * g + u.clamp(0, g - 1).long()
        cell += (torch.arange(b, device=c2w.device) * (g * g)).unsqueeze(1)
        zbuf = torch.full((b * g * g,), float("inf"), dtype=dt, device=c2w.device)
        zbuf = zbuf.scatter_reduce(0, cell[ok], z[ok], reduce="amin")
        n_occ = ox.shape[1]
        sc, sz, s_ok = cell[:, n_occ:], z[:, n_occ:], ok[:, n_occ:]
        covered: dict[int, Tensor] = {}
        vis = torch.zeros(b, s, dtype=dt, device=c2w.device)
        for k_d, tol in self.occ_tests:
            if k_d not in covered:
                # every occluder covers a k_d x k_d square: a min-filter of the depth buffer
                # (empty cells hold +inf, which the max-pool of -zbuf handles as is)
                covered[k_d] = zbuf if k_d == 1 else -torch.nn.functional.max_pool2d(
                    -zbuf.reshape(b, 1, g, g), k_d, stride=1, padding=k_d // 2
                ).reshape(-1)
            vis += (s_ok & (sz <= covered[k_d][sc] * (1.0 + tol))).to(dt)
        return vis / len(self.occ_tests)

    def uses_kernel(self, c2w: Tensor) -> bool:
        """Whether :meth:`__call__` runs the compiled kernel for poses ``c2w`` (the backend
        allows it: :func:`agilegs.service.nbv.kernels.backend.resolve`; and the visibility is the
        transmittance or none: the z-buffer test has no kernel)."""
        if self.grid is None and self.occluders is not None:
            return False
        if self.rate is not None and self.rate.ndim == 2 and self.axes is None:
            return False
        return (gpu_proxy.gpu_proxy_applies(None, c2w, self.means)  # CUDA: Triton's
                or backend.resolve(None, (c2w, self.means)))

    def __call__(self, c2w: Tensor, per_sample: bool = False) -> Tensor:
        """psi for poses [B, 4, 4] -> [B] (differentiable in the poses, but for visibility).

        The compiled kernel (:mod:`agilegs.service.nbv.kernels.proxy`) serves where
        :meth:`uses_kernel` says so, differentiable in the poses through its analytic
        gradient; :meth:`reference` is the pure-torch path, which it equals.
        """
        if self.uses_kernel(c2w):
            if per_sample:
                if c2w.requires_grad and torch.is_grad_enabled():
                    return self.reference(c2w, per_sample=True)
                return self._kernel(c2w, want_grad=False, per_sample=True)[0]
            return _ProxyKernel.apply(c2w, self)
        return self.reference(c2w, per_sample)

    def _kernel_inputs(self) -> dict[str, Any]:
        """The samples, the model and the visibility as the kernel's float64 arrays (built
        once per proxy)."""
        cached = getattr(self, "_knp", None)
        if cached is not None:
            return cached
        f64 = torch.float64

        def arr(t: Tensor) -> np.ndarray:
            return np.ascontiguousarray(t.detach().to(f64).cpu().numpy())

        s = self.means.shape[0]
        k = self.intrinsics
        if self.rate is None:
            mode, rate = 0, np.zeros((s, 1))
        elif self.rate.ndim == 1:
            mode, rate = 1, arr(self.rate.reshape(-1, 1))
        else:
            mode, rate = 2, arr(self.rate)
        kinds = (np.ascontiguousarray(self.slot_kinds.cpu().numpy().astype(np.int64))
                 if mode == 2 and self.slot_kinds is not None else np.zeros(1, dtype=np.int64))
        axes = (arr(self.axes.reshape(-1, 9)) if mode == 2 and self.axes is not None
                else np.zeros((1, 9)))
        grid = self.grid
        if grid is not None:
            occ, mass = arr(grid.means), arr(grid.mass)
            c = grid.center.detach().to(f64).cpu()
            vis = np.array([float(c[0]), float(c[1]), float(c[2]), grid.half_depth, 1.0])
            cells, bins = grid.cells, grid.bins
        else:
            occ, mass = np.zeros((0, 3)), np.zeros(0)
            vis = np.array([0.0, 0.0, 0.0, 1.0, 0.0])
            cells, bins = 1, 1
        out = dict(
            intr=np.array([k.fx, k.fy, k.cx, k.cy, float(k.width), float(k.height),
                           float(self.near), float(self.edge)]),
            means=arr(self.means), sigma6=arr(self.sigma6.T), weight=arr(self.weight),
            rate=rate, kinds=kinds, axes=axes, mode=mode, occ=occ, mass=mass, vis_prm=vis,
            cells=int(cells), bins=int(bins),
        )
        self._knp = out
        return out

    def terms_and_factors(self, c2w: Tensor, axes: Tensor) -> tuple[Tensor, Tensor]:
        """The per-sample terms from poses [B, 4, 4] -> [B, S], and the terms times each
        direction factor (:func:`direction_factors` with the samples' local axes ``axes``
        [S, 3, 3]) summed over the poses -> [S, 7]; through the kernel where
        :meth:`uses_kernel` says so (no gradient)."""
        if self.uses_kernel(c2w):
            terms, acc = self._kernel(c2w, want_grad=False, per_sample=True, axes=axes)
            assert acc is not None
            return terms, acc
        dt = c2w.dtype
        w = self.reference(c2w, per_sample=True)
        f = direction_factors(self.means.to(dt), c2w[:, :3, 3], axes.to(dt))
        return w, (w.unsqueeze(-1) * f).sum(0)

    def values_in_parts(self, c2w: Tensor, part: int, between: Callable[[], None]
                        ) -> Tensor:
        """psi for poses [B, 4, 4] -> [B] without gradient, ``part`` poses at a time with
        ``between()`` called before each part (a cancellation check): through the kernel
        (the poses converted once, the parts as ranges of one array) where
        :meth:`uses_kernel` says so, else parts of :meth:`reference`."""
        if not self.uses_kernel(c2w):
            parts = []
            for i in range(0, c2w.shape[0], part):
                between()
                with torch.no_grad():
                    parts.append(self.reference(c2w[i : i + part]))
            return torch.cat(parts) if parts else c2w.new_zeros(0)
        return self._kernel(c2w, want_grad=False, part=part, between=between)[0]

    def _kernel(self, c2w: Tensor, want_grad: bool, per_sample: bool = False,
                axes: Tensor | None = None, part: int = 0,
                between: Callable[[], None] | None = None) -> tuple[Tensor, Tensor | None]:
        """The kernel at poses [B, 4, 4]: psi [B] (or the per-sample terms [B, S]) and, with
        ``want_grad``, d psi / d c2w [B, 4, 4] (zero in the last row); with ``per_sample``
        and ``axes`` [S, 3, 3], the terms and their sum over the poses times each direction
        factor [S, 7] (:meth:`terms_and_factors`). ``part`` > 0: the poses in ranges of that
        many, ``between()`` called before each."""
        if gpu_proxy.gpu_proxy_applies(None, c2w, self.means):  # Triton's, all poses at once
            return gpu_proxy.proxy_kernel(self, c2w, want_grad, per_sample, axes, between)
        kin = self._kernel_inputs()
        b = c2w.shape[0]
        pose = c2w.detach().to(torch.float64).cpu()
        cams = np.ascontiguousarray(
            torch.cat([pose[:, :3, :3].reshape(b, 9), pose[:, :3, 3]], dim=1).numpy())
        psi = np.zeros(b)
        grad = np.zeros((b, 12) if want_grad else (1, 12))
        s = int(kin["means"].shape[0])
        terms = np.zeros((b, s) if per_sample else (1, 1))
        fn = backend.kernel_module().proxy_psi
        accumulate = per_sample and axes is not None
        acc = np.zeros((s, 7) if accumulate else (1, 7))
        ax = (np.ascontiguousarray(axes.detach().to(torch.float64).cpu().reshape(-1, 9).numpy())
              if accumulate and axes is not None else kin["axes"])

        def run(b0: int, b1: int, offset: int = 0) -> None:
            fn(cams, kin["intr"], kin["means"], kin["sigma6"], kin["weight"], kin["rate"],
               kin["kinds"], ax, kin["mode"], kin["occ"], kin["mass"], kin["vis_prm"],
               kin["cells"], kin["bins"], want_grad, per_sample, offset + b0, offset + b1,
               psi, grad, terms, accumulate, acc)

        if accumulate:
            run(0, b)  # the poses add to the same rows: one thread
        elif part > 0:
            for b0 in range(0, b, part):
                if between is not None:
                    between()
                backend.run_in_parts(functools.partial(run, offset=b0), min(b, b0 + part) - b0)
        else:
            backend.run_in_parts(run, b)
        dt, dev = c2w.dtype, c2w.device
        if per_sample:
            return (torch.from_numpy(terms).to(device=dev, dtype=dt),
                    torch.from_numpy(acc).to(device=dev, dtype=dt) if accumulate else None)
        out = torch.from_numpy(psi).to(device=dev, dtype=dt)
        if not want_grad:
            return out, None
        g = torch.zeros(b, 4, 4, dtype=dt, device=dev)
        gt = torch.from_numpy(grad).to(device=dev, dtype=dt)
        g[:, :3, :3] = gt[:, :9].reshape(b, 3, 3)
        g[:, :3, 3] = gt[:, 9:]
        return out, g

    def reference(self, c2w: Tensor, per_sample: bool = False) -> Tensor:
        """The pure-torch psi for poses [B, 4, 4] -> [B] (differentiable in the poses, but
        for the z-buffer visibility): the reference the kernel is tested against.

        ``per_sample``: return the unweighted per-sample terms footprint x inside x visible
        [B, S] instead of their weighted sum.

        The 2D covariance ``J W Sigma W^T J^T`` is formed from the six quadratic forms
        ``e_a^T Sigma e_b`` of the camera axes (one small GEMM for all poses and samples):
        with ``t = (x/z, y/z)``, row 1 of ``J W`` is ``fx/z (e_x - t_x e_z)`` and row 2
        ``fy/z (e_y - t_y e_z)``.
        """
        k = self.intrinsics
        dt = c2w.dtype
        rot = c2w[:, :3, :3]
        x, y, z = to_camera(self.means.to(dt), rot, c2w[:, :3, 3])  # each [B, S]
        # smooth positive depth (softplus above the near plane): finite Jacobians behind it
        zs = self.near + torch.nn.functional.softplus(z - self.near, beta=20.0 / self.near)
        tx, ty = x / zs, y / zs
        ex, ey, ez = rot[:, :, 0], rot[:, :, 1], rot[:, :, 2]  # camera axes in world [B, 3]
        pairs = [(ex, ex), (ex, ey), (ex, ez), (ey, ey), (ey, ez), (ez, ez)]
        # w[b, p] . sigma6[s] = e_a^T Sigma_s e_b with sigma6 = (xx, yy, zz, 2xy, 2xz, 2yz)
        w = torch.stack(
            [
                torch.stack(
                    [
                        a[:, 0] * c[:, 0],
                        a[:, 1] * c[:, 1],
                        a[:, 2] * c[:, 2],
                        0.5 * (a[:, 0] * c[:, 1] + a[:, 1] * c[:, 0]),
                        0.5 * (a[:, 0] * c[:, 2] + a[:, 2] * c[:, 0]),
                        0.5 * (a[:, 1] * c[:, 2] + a[:, 2] * c[:, 1]),
                    ],
                    dim=-1,
                )
                for a, c in pairs
            ],
            dim=1,
        )  # [B, 6, 6]
        sig = self.sigma6.to(dt)  # [6, S]
        q = torch.matmul(w, sig)  # [B, 6, S]
        qxx, qxy, qxz, qyy, qyz, qzz = q.unbind(1)
        iz2 = 1.0 / (zs * zs)
        a = k.fx * k.fx * iz2 * (qxx - 2 * tx * qxz + tx * tx * qzz) + 0.3
        bb = k.fx * k.fy * iz2 * (qxy - tx * qyz - ty * qxz + tx * ty * qzz)
        cc = k.fy * k.fy * iz2 * (qyy - 2 * ty * qyz + ty * ty * qzz) + 0.3
        foot = torch.sqrt((a * cc - bb * bb).clamp_min(1e-12))
        terms = foot * self._inside(x, y, z) * self.visibility(c2w, (x, y, z))
        return self._reduce(c2w, terms, per_sample)

    def _reduce(self, c2w: Tensor, terms: Tensor, per_sample: bool) -> Tensor:
        """The model's sum over the samples of the per-sample terms [B, S] -> [B] (or the
        terms as they are, ``per_sample``)."""
        dt = c2w.dtype
        if per_sample:
            return terms
        if self.rate is not None and self.rate.ndim == 2:
            assert self.slot_kinds is not None
            f = self.direction_factors(c2w)[..., self.slot_kinds]  # [B, S, Q]
            terms = torch.log1p(terms.unsqueeze(-1) * f * self.rate.to(dt)).sum(-1)
        elif self.rate is not None:
            terms = torch.log1p(terms * self.rate.to(dt))
        return terms @ self.weight.to(dt)

    def _inside(self, x: Tensor, y: Tensor, z: Tensor) -> Tensor:
        """The smooth in-frustum test of camera coordinates (each [B, S]) -> [B, S]."""
        k = self.intrinsics
        zs = self.near + torch.nn.functional.softplus(z - self.near, beta=20.0 / self.near)
        u = k.fx * x / zs + k.cx
        v = k.fy * y / zs + k.cy
        e = self.edge
        return (
            torch.sigmoid((z - self.near) / (0.25 * self.near))
            * torch.sigmoid(u / e)
            * torch.sigmoid((k.width - u) / e)
            * torch.sigmoid(v / e)
            * torch.sigmoid((k.height - v) / e)
        )

    def seen(self, c2w: Tensor) -> Tensor:
        """How much of each sample a pose sees, inside x visible, from poses [B, 4, 4] ->
        [B, S] (the footprint left out)."""
        x, y, z = to_camera(self.means.to(c2w.dtype), c2w[:, :3, :3], c2w[:, :3, 3])
        return self._inside(x, y, z) * self.visibility(c2w, (x, y, z))

    def extended(self, means: Tensor, cov: Tensor, weight: Tensor, rate: Tensor | None
                 ) -> ProxyPsi:
        """This proxy with extra samples appended: centres [E, 3], covariances [E, 3, 3],
        weights [E] and rates ([E] or [E, Q], as this proxy's; None for the linear form).
        Their local axes (directional form) are the world axes."""
        dt = self.means.dtype
        axes = None
        if self.axes is not None:
            eye = torch.eye(3, dtype=dt, device=means.device).expand(means.shape[0], 3, 3)
            axes = torch.cat([self.axes, eye])
        new_rate = None
        if self.rate is not None:
            if rate is None:
                raise ValueError("a proxy with rates needs the extra samples' rates")
            new_rate = torch.cat([self.rate, rate.to(dt)])
        return dataclasses.replace(
            self,
            means=torch.cat([self.means, means.to(dt)]),
            cov=torch.cat([self.cov, cov.to(dt)]),
            weight=torch.cat([self.weight, weight.to(self.weight.dtype)]),
            rate=new_rate,
            axes=axes,
        )

    def direction_factors(self, c2w: Tensor) -> Tensor:
        """:func:`direction_factors` of the samples from poses [B, 4, 4] -> [B, S, 7]."""
        return direction_factors(self.means.to(c2w.dtype), c2w[:, :3, 3],
                                 None if self.axes is None else self.axes.to(c2w.dtype))

    def __post_init__(self) -> None:
        c = self.cov
        #: the covariances as (xx, yy, zz, 2xy, 2xz, 2yz) [6, S]
        self.sigma6 = torch.stack(
            [c[:, 0, 0], c[:, 1, 1], c[:, 2, 2], 2 * c[:, 0, 1], 2 * c[:, 0, 2], 2 * c[:, 1, 2]]
        )


DIRECTION_KINDS = ("isotropic", "world_x", "world_y", "world_z", "local_0", "local_1",
                   "local_2")
"""The direction factors of :func:`direction_factors`, in order."""


class _ProxyKernel(torch.autograd.Function):
    """psi of poses [B, 4, 4] -> [B] through the compiled kernel, with its analytic gradient
    in the poses."""

    @staticmethod
    def forward(ctx: Any, c2w: Tensor, proxy: ProxyPsi) -> Tensor:  # type: ignore[override]
        want = bool(ctx.needs_input_grad[0])
        psi, grad = proxy._kernel(c2w, want_grad=want)
        ctx.save_for_backward(grad if grad is not None else torch.zeros(0))
        return psi

    @staticmethod
    def backward(ctx: Any, grad_out: Tensor) -> tuple[Tensor | None, None]:  # type: ignore[override]
        (grad,) = ctx.saved_tensors
        if grad.numel() == 0:
            return None, None
        return grad_out[:, None, None] * grad, None


def local_axes(quats: Tensor) -> Tensor:
    """The local axes of Gaussians with quaternions (w, x, y, z) [N, 4], as the columns of
    their rotation matrices [N, 3, 3]."""
    return quat_to_rotmat(quats)


def direction_factors(points: Tensor, centres: Tensor, axes: Tensor | None) -> Tensor:
    """How much a view from each camera centre [B, 3] tells about a direction-bound parameter
    of each point [S, 3]: [B, S, 7], in :data:`DIRECTION_KINDS` order.

    With d the unit ray from the camera centre to the point: 1 for isotropic parameters
    (opacity, colour, rotation), ``1 - d_k^2`` for the world axis k of a mean (a pinhole
    camera sees a mean move across its rays, not along them) and ``1 - (d . u_k)^2`` for the
    local axis u_k of a scale (``axes`` [S, 3, 3], columns u_k; 1 without axes).
    """
    d = points.unsqueeze(0) - centres.unsqueeze(1)  # [B, S, 3]
    d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    world = 1.0 - d * d
    if axes is None:
        local = torch.ones_like(world)
    else:
        c = torch.einsum("bsk,skj->bsj", d, axes)
        local = 1.0 - c * c
    return torch.cat([torch.ones_like(world[..., :1]), world, local], dim=-1)


def to_camera(points: Tensor, rot: Tensor, t: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Camera coordinates x, y, z (each [B, P]) of world points [P, 3] for c2w rotations
    [B, 3, 3] and centres [B, 3]: one GEMM ``(R^T) [3B, 3] @ points^T [3, P]``."""
    b = rot.shape[0]
    rt = rot.transpose(1, 2)  # rows: the camera axes in world
    cam = torch.matmul(rt.reshape(3 * b, 3), points.T.contiguous()).reshape(b, 3, -1)
    cam = cam - torch.matmul(rt, t.unsqueeze(-1))  # [B, 3, 1]
    return cam[:, 0], cam[:, 1], cam[:, 2]
