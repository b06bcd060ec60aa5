"""Where the anchor may go: the pool's envelope (radius and elevation range, aimed at the map).

Every iterate of the ascent is projected back into the radius and elevation range of the pool
around the pool's centre and, if it looks further away from the map centre than any pool
camera does, turned back towards it: this keeps the anchor out of degenerate poses (inside the
object, looking at nothing, far outside the reachable set).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..rotations import axis_angle_to_matrix

__all__ = ["PoolEnvelope"]


@dataclass
class PoolEnvelope:
    """Where the anchor may go: the radius and elevation range of the pool, aimed at the map.

    Attributes:
        centre: the point the pool's cameras look at (least-squares crossing of their
            optical axes) [3].
        up: world up, from the pool cameras' -y axes [3].
        r_min, r_max: range of camera distances from ``centre``.
        elev_min, elev_max: range of camera elevations (radians) above the plane through
            ``centre`` perpendicular to ``up``.
        aim: the map centre [3].
        max_off_aim: the largest angle (radians) between a pool camera's optical axis and
            its direction to ``aim``.
        radius: typical (median) camera distance, the unit of the twist metric.
    """

    centre: Tensor
    up: Tensor
    r_min: float
    r_max: float
    elev_min: float
    elev_max: float
    aim: Tensor
    max_off_aim: float
    radius: float

    @classmethod
    def from_pool(cls, candidates: Tensor, aim: Tensor, margin: float = 0.05) -> PoolEnvelope:
        """The envelope of pool poses [D, 4, 4] around the map centre ``aim`` [3]."""
        c = candidates.detach()
        dt, dev = c.dtype, c.device
        p = c[:, :3, 3]
        d = c[:, :3, 2]
        eye = torch.eye(3, dtype=dt, device=dev)
        proj = eye - d.unsqueeze(-1) * d.unsqueeze(-2)  # [D, 3, 3]
        a = proj.sum(0) + 1e-6 * eye * len(c)
        rhs = (proj @ p.unsqueeze(-1)).sum(0).squeeze(-1) + 1e-6 * len(c) * p.mean(0)
        centre = torch.linalg.solve(a, rhs)
        up = -c[:, :3, 1].mean(0)
        up = up / up.norm().clamp_min(1e-12)
        rel = p - centre
        r = rel.norm(dim=1)
        elev = torch.asin(((rel @ up) / r.clamp_min(1e-12)).clamp(-1, 1))
        to_aim = aim.to(dt) - p
        to_aim = to_aim / to_aim.norm(dim=1, keepdim=True).clamp_min(1e-12)
        off = torch.arccos((to_aim * d).sum(1).clamp(-1, 1))
        return cls(
            centre=centre,
            up=up,
            r_min=float(r.min()) * (1 - margin),
            r_max=float(r.max()) * (1 + margin),
            elev_min=max(float(elev.min()) - margin, -math.pi / 2 + 1e-3),
            elev_max=min(float(elev.max()) + margin, math.pi / 2 - 1e-3),
            aim=aim.to(dt),
            max_off_aim=float(off.max()) + margin,
            radius=max(float(r.median()), 1e-6),
        )

    def project(self, c2w: Tensor) -> Tensor:
        """Poses [B, 4, 4] moved into the envelope (differentiable almost everywhere)."""
        dt = c2w.dtype
        centre, up, aim = self.centre.to(dt), self.up.to(dt), self.aim.to(dt)
        p = c2w[:, :3, 3]
        rel = p - centre
        r = rel.norm(dim=1, keepdim=True).clamp_min(1e-9)
        h = rel - (rel @ up).unsqueeze(1) * up
        hn = h.norm(dim=1, keepdim=True)
        fallback = torch.linalg.cross(up.expand_as(p), c2w[:, :3, 0])  # looking straight down/up
        h_dir = torch.where(hn > 1e-9, h / hn.clamp_min(1e-12), fallback)
        h_dir = h_dir / h_dir.norm(dim=1, keepdim=True).clamp_min(1e-12)
        elev = torch.asin(((rel @ up).unsqueeze(1) / r).clamp(-1, 1))
        elev_c = elev.clamp(self.elev_min, self.elev_max)
        r_c = r.clamp(self.r_min, self.r_max)
        new_p = centre + r_c * (torch.cos(elev_c) * h_dir + torch.sin(elev_c) * up)
        rot = c2w[:, :3, :3]
        f = rot[:, :, 2]
        to_aim = aim - new_p
        to_aim = to_aim / to_aim.norm(dim=1, keepdim=True).clamp_min(1e-12)
        cosang = (f * to_aim).sum(1).clamp(-1, 1)
        ang = torch.arccos(cosang)
        excess = (ang - self.max_off_aim).clamp_min(0.0)
        axis = torch.linalg.cross(f, to_aim)
        an = axis.norm(dim=1, keepdim=True)
        need = (excess > 0) & (an.squeeze(1) > 1e-9)
        axis = torch.where(an > 1e-9, axis / an.clamp_min(1e-12), torch.zeros_like(axis))
        fix = axis_angle_to_matrix(axis, torch.where(need, excess, torch.zeros_like(excess)))
        out = c2w.clone()
        out[:, :3, :3] = fix @ rot
        out[:, :3, 3] = new_p
        return out

    def contains(self, c2w: Tensor, tol: float = 1e-4) -> Tensor:
        """Whether poses [B, 4, 4] lie inside the envelope [B] (bool)."""
        p = c2w[:, :3, 3]
        rel = p - self.centre.to(p.dtype)
        r = rel.norm(dim=1)
        elev = torch.asin(((rel @ self.up.to(p.dtype)) / r.clamp_min(1e-12)).clamp(-1, 1))
        to_aim = self.aim.to(p.dtype) - p
        to_aim = to_aim / to_aim.norm(dim=1, keepdim=True).clamp_min(1e-12)
        ang = torch.arccos((to_aim * c2w[:, :3, 2]).sum(1).clamp(-1, 1))
        rtol = tol * self.radius
        return (
            (r >= self.r_min - rtol)
            & (r <= self.r_max + rtol)
            & (elev >= self.elev_min - tol)
            & (elev <= self.elev_max + tol)
            & (ang <= self.max_off_aim + tol)
        )
