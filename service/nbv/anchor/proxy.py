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

from dataclasses import dataclass

import torch
from torch import Tensor

from agilegs.config.selection import POINT_ZBUFFER

from ..camera import Intrinsics
from ..gaussians import GaussianMap
from ..projection import covariance_3d
from .visibility import OpacityMaps

__all__ = ["ProxyPsi", "pick_occluders", "to_camera"]


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
    ``psi(T) = sum_s weight_s * log(1 + rate_s * w_s(T))`` when ``rate`` is set (the fitted
    model, ``observation_rates``), else ``psi(T) = sum_s weight_s * w_s(T)``. ``visible_s``:
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
        rate: per-sample rate a_s of the log form [S] (None: the linear form).
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
    ) -> ProxyPsi:
        """Importance-sample ``num_samples`` Gaussians with probability ~ c [N] (seeded).

        Linear form (``rate`` None): ``psi = sum_i c_i w_i``, estimated by the sample.
        Log form (``rate`` [N]): ``psi = sum_i slots * log(1 + rate_i w_i)``, estimated by the
        sample drawn ~ c (c_i should be that Gaussian's typical term) and reweighted by
        ``1 / c_i``. ``num_samples`` 0 or >= N takes every Gaussian once, unweighted.
        ``grid`` gives the transmittance visibility; without it, ``num_occluders`` > 0
        enables the z-buffer test with that many opaque Gaussians (opacity >= ``min_opacity``;
        all of them when fewer) as occluders, or with ``occluders`` [M, 3] when given; 0
        disables it.
        """
        c = c.detach().clamp_min(0)
        n = c.shape[0]
        total = float(c.sum())
        if num_samples == 0 or num_samples >= n or total <= 0:
            idx = torch.arange(n, device=c.device)
            w = c if rate is None else torch.full_like(c, float(slots))
        else:
            draws = torch.multinomial(
                c.cpu().double(), num_samples, replacement=True, generator=generator
            )
            uniq, counts = torch.unique(draws, return_counts=True)
            idx = uniq.to(c.device)
            w = counts.to(device=c.device, dtype=c.dtype) * (total / num_samples)
            if rate is not None:
                w = w * float(slots) / c[idx].clamp_min(1e-30)
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

    def __call__(self, c2w: Tensor, per_sample: bool = False) -> Tensor:
        """psi for poses [B, 4, 4] -> [B] (differentiable in the poses, but for visibility).

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
        t = c2w[:, :3, 3]
        x, y, z = to_camera(self.means.to(dt), rot, t)  # each [B, S]
        # smooth positive depth (softplus above the near plane): finite Jacobians behind it
        zs = self.near + torch.nn.functional.softplus(z - self.near, beta=20.0 / self.near)
        tx, ty = x / zs, y / zs
        u = k.fx * tx + k.cx
        v = k.fy * ty + k.cy
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
        e = self.edge
        inside = (
            torch.sigmoid((z - self.near) / (0.25 * self.near))
            * torch.sigmoid(u / e)
            * torch.sigmoid((k.width - u) / e)
            * torch.sigmoid(v / e)
            * torch.sigmoid((k.height - v) / e)
        )
        vis = self.visibility(c2w, (x, y, z))
        terms = foot * inside * vis
        if per_sample:
            return terms
        if self.rate is not None:
            terms = torch.log1p(terms * self.rate.to(dt))
        return terms @ self.weight.to(dt)

    def __post_init__(self) -> None:
        c = self.cov
        #: the covariances as (xx, yy, zz, 2xy, 2xz, 2yz) [6, S]
        self.sigma6 = torch.stack(
            [c[:, 0, 0], c[:, 1, 1], c[:, 2, 2], 2 * c[:, 0, 1], 2 * c[:, 0, 2], 2 * c[:, 1, 2]]
        )


def to_camera(points: Tensor, rot: Tensor, t: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Camera coordinates x, y, z (each [B, P]) of world points [P, 3] for c2w rotations
    [B, 3, 3] and centres [B, 3]: one GEMM ``(R^T) [3B, 3] @ points^T [3, P]``."""
    b = rot.shape[0]
    rt = rot.transpose(1, 2)  # rows: the camera axes in world
    cam = torch.matmul(rt.reshape(3 * b, 3), points.T.contiguous()).reshape(b, 3, -1)
    cam = cam - torch.matmul(rt, t.unsqueeze(-1))  # [B, 3, 1]
    return cam[:, 0], cam[:, 1], cam[:, 2]
