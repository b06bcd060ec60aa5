"""One entry point for every next-best-view method: ``select``.

Methods (paper sections 3-5 and its baselines), all on the same map, Hhat and pool:

- ``random``: seeded uniform choice among the eligible candidates.
- ``fisherrf``: the EIG phi(v) = sum_q log(1 + H_v,qq / Hhat_qq) of every eligible candidate
  (one exact ``fisher_diag`` pass per candidate), argmax.
- ``cover``: COVER's coverage score (``agilegs.service.nbv.cover``), argmin.
- ``agile``: anchor T* = argmax psi (``anchor``), coverage matrix M of the eligible
  candidates against T*'s support samples (``coverage``), B = M Pi (fixed seeded JL), a
  shortlist of N rows, and the shortlist's first.
- ``agile_plus``: the same shortlist, reranked by phi; the argmax.

The shortlist strategy of ``agile`` / ``agile_plus`` is ``SelectConfig.shortlist``:
``leverage`` (the paper's greedy ridge leverage), or the ablations ``knearest`` (the N
candidates nearest the anchor under the SE(3) distance ``se3.pose_distance``), ``topnorm``
(the N largest ||b_v||) and ``online`` (online lambda-ridge leverage row sampling).

Embodied mode (``SelectConfig.embodied_k = K``): only the K candidates nearest the current
view (``current`` index, which is itself excluded, or ``current_pose``) under the same SE(3)
distance are eligible; the anchor's starts are then drawn from them too, so that the anchor
stays in the reachable neighbourhood.

Every random choice (random pick, importance sampling of the proxy, support samples, online
sampling) is drawn from generators seeded with ``SelectConfig.seed`` and the event counter
kept in ``state``, so the same seed and state give the same selection. The JL matrix depends
on the seed only: it is fixed across events.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import torch
from torch import Tensor

from .anchor import AnchorConfig, PoolEnvelope, optimize_anchor, typical_fisher_from_views
from .camera import Camera, Intrinsics, check_pose
from .candidates import scene_center_radius
from .cover import cover_scores
from .coverage import coverage_matrix, jl_projection, support_samples
from .gaussians import FIELD_NAMES, GaussianMap
from .information import fisher_diag
from .leverage import (
    greedy_ridge_leverage_gains,
    online_ridge_leverage,
    topnorm_shortlist,
)
from .se3 import pose_distance

__all__ = [
    "METHODS",
    "SHORTLISTS",
    "AnchorConfig",
    "ScoringConfig",
    "SelectConfig",
    "Selection",
    "eig_scores",
    "eligible_candidates",
    "select",
]

METHODS: tuple[str, ...] = ("random", "fisherrf", "cover", "agile", "agile_plus")
SHORTLISTS: tuple[str, ...] = ("leverage", "knearest", "topnorm", "online")
STAGES: tuple[str, ...] = ("anchor", "scoring", "leverage", "rerank", "total")

Method = Literal["random", "fisherrf", "cover", "agile", "agile_plus"]
Shortlist = Literal["leverage", "knearest", "topnorm", "online"]


@dataclass
class ScoringConfig:
    """Candidate scoring against the anchor (paper section 4.2) and the shortlist maths.

    Args:
        grid: edge of the point z-buffer grid giving the surface support samples (64).
        ray_samples: extra support samples along the anchor ray per surface sample (1).
        ray_min_fraction: ray samples lie in [this, 1) x the surface depth (0.5).
        max_samples: K, at most this many support samples (2048; a seeded subset beyond).
        min_opacity: Gaussians below this opacity are not surface samples (0.05).
        jl_dim: d, the Johnson-Lindenstrauss dimension (64).
        sigma_p: positional tolerance of rho in world units (None: 0.5 x the pool's median
            camera distance from its centre).
        gamma: sharpness of the row weight rho^gamma (1.0).
        eps: the inverse-range regulariser, relative to the pool radius (1e-3).
        ridge: lambda_G relative to the largest ||b_v||^2 (1e-2), so that the shortlist does
            not depend on the scene's units; ``ridge_absolute`` uses it as is.
        ridge_absolute: take ``ridge`` as the absolute lambda_G (False).
        online_oversample: oversampling of the ``online`` shortlist (1.0 ~ N rows per pass).
        rot_weight: world units per radian in the SE(3) distance of ``knearest`` and embodied
            mode (None: the pool's median camera distance from its centre, so that moving one
            radian along an orbit counts the same as turning by one radian).
        near: near plane of the frustum tests (0.01 world units).
        condition_on_acquired: the ``leverage`` shortlist starts from the acquired views'
            rows (scored against the anchor like the candidates): ``S_0 = lambda_G I +
            B_acq^T B_acq`` instead of ``lambda_G I``, so that a candidate repeating what an
            acquired view already covers of the anchor's volume has low leverage (True; the
            paper conditions on the shortlist only, which is False).
    """

    grid: int = 64
    ray_samples: int = 1
    ray_min_fraction: float = 0.5
    max_samples: int = 2048
    min_opacity: float = 0.05
    jl_dim: int = 64
    sigma_p: float | None = None
    gamma: float = 1.0
    eps: float = 1e-3
    ridge: float = 1e-2
    ridge_absolute: bool = False
    online_oversample: float = 1.0
    rot_weight: float | None = None
    near: float = 0.01
    condition_on_acquired: bool = True

    def validate(self) -> None:
        for name in ("grid", "max_samples", "jl_dim"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"scoring.{name} must be >= 1, got {getattr(self, name)}")
        if self.ray_samples < 0:
            raise ValueError(f"scoring.ray_samples must be >= 0, got {self.ray_samples}")
        for name in ("gamma", "eps", "ridge", "online_oversample", "near"):
            v = float(getattr(self, name))
            if not (v > 0 and math.isfinite(v)):
                raise ValueError(f"scoring.{name} must be positive and finite, got {v}")
        for name in ("sigma_p", "rot_weight"):
            v = getattr(self, name)
            if v is not None and not (float(v) > 0 and math.isfinite(float(v))):
                raise ValueError(f"scoring.{name} must be positive and finite or None, got {v}")


@dataclass
class SelectConfig:
    """Settings of ``select``; every field settable per call.

    Args:
        shortlist_size: N, the shortlist budget of agile / agile_plus (10, as in the paper).
        shortlist: the shortlist strategy: "leverage" (paper), "knearest", "topnorm",
            "online" (ablations).
        embodied_k: only the K nearest candidates to the current view are eligible (None:
            all; the paper's embodied protocol uses 5).
        seed: seeds every random choice (0).
        fields: parameter blocks entering phi and psi (None: all five).
        anchor: anchor settings (``AnchorConfig``).
        scoring: candidate-scoring settings (``ScoringConfig``).
        cover_bins: COVER's direction bins per Gaussian (128, as COVER's code).
        cover_resolution: COVER's render width (None: the candidates' own).
        fisher_background: background colour [3] of the Fisher renders (None: black).
    """

    shortlist_size: int = 10
    shortlist: Shortlist = "leverage"
    embodied_k: int | None = None
    seed: int = 0
    fields: tuple[str, ...] | None = None
    anchor: AnchorConfig = field(default_factory=AnchorConfig)
    scoring: ScoringConfig = field(default_factory=ScoringConfig)
    cover_bins: int = 128
    cover_resolution: int | None = None
    fisher_background: tuple[float, float, float] | None = None

    def validate(self) -> None:
        n = self.shortlist_size
        if isinstance(n, bool) or int(n) != n or int(n) < 1:
            raise ValueError(
                f"config.shortlist_size (the budget N) must be an integer >= 1, got {n!r}"
            )
        if self.shortlist not in SHORTLISTS:
            raise ValueError(
                f"config.shortlist must be one of {SHORTLISTS}, got {self.shortlist!r}"
            )
        if self.embodied_k is not None and (
            isinstance(self.embodied_k, bool) or int(self.embodied_k) < 1
        ):
            raise ValueError(f"config.embodied_k must be >= 1 or None, got {self.embodied_k!r}")
        if self.fields is not None:
            if len(self.fields) == 0:
                raise ValueError("config.fields must name at least one parameter block")
            for f in self.fields:
                if f not in FIELD_NAMES:
                    raise ValueError(f"config.fields: unknown block {f!r} (known: {FIELD_NAMES})")
        if self.cover_bins < 1:
            raise ValueError(f"config.cover_bins must be >= 1, got {self.cover_bins}")
        self.anchor.validate()
        self.scoring.validate()


@dataclass
class Selection:
    """The outcome of one ``select`` call.

    Attributes:
        method: the method that chose.
        index: the chosen candidate, an index into ``candidates``.
        shortlist: the ordered shortlist (indices into ``candidates``; [] without one).
        anchor_c2w: the anchor pose [4, 4] (agile / agile_plus), else None.
        psi_trace: psi at the winning start and after each accepted ascent step ([] if none).
        scores: per-candidate scores where computed: phi (fisherrf, agile_plus shortlist),
            COVER score (cover), conditional leverage at pick time (agile with "leverage"),
            ||b|| (topnorm), distance to the anchor (knearest), online leverage (online).
        eligible: the eligible candidates (all but embodied mode's restriction).
        latency_ms: milliseconds per stage: anchor, scoring, leverage, rerank, total.
        state: warm-start state for the next call (the anchor, the event counter, ...).
        details: diagnostics (support sample count, psi evaluations, proxy psi of the pool).
    """

    method: str
    index: int
    shortlist: list[int]
    anchor_c2w: Tensor | None
    psi_trace: list[float]
    scores: dict[int, float]
    eligible: list[int]
    latency_ms: dict[str, float]
    state: dict[str, Any]
    details: dict[str, Any] = field(default_factory=dict)


# ----------------------------------------------------------------------------- validation
def _validate(
    method: str,
    gmap: GaussianMap,
    h_acc: Mapping[str, Tensor],
    candidates: Tensor,
    intrinsics: Intrinsics,
    acquired: Tensor | None,
    current: int | None,
    current_pose: Tensor | None,
    config: SelectConfig,
    fields: tuple[str, ...],
) -> None:
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if not isinstance(gmap, GaussianMap):
        raise TypeError(f"gmap must be a GaussianMap, got {type(gmap).__name__}")
    if gmap.num_gaussians == 0:
        raise ValueError("gmap has no Gaussians")
    if not isinstance(intrinsics, Intrinsics):
        raise TypeError(f"intrinsics must be an Intrinsics, got {type(intrinsics).__name__}")
    if (
        not isinstance(candidates, Tensor)
        or candidates.ndim != 3
        or candidates.shape[1:]
        != (
            4,
            4,
        )
    ):
        raise ValueError(
            f"candidates must be a tensor of poses [D, 4, 4], got "
            f"{list(getattr(candidates, 'shape', [])) or type(candidates).__name__}"
        )
    if candidates.shape[0] == 0:
        raise ValueError("candidates is empty: the pool needs at least one pose")
    check_pose(candidates, "candidates")
    config.validate()
    if not isinstance(h_acc, Mapping):
        raise ValueError(f"h_acc must be a dict of per-field tensors, got {type(h_acc).__name__}")
    for f in fields:
        if f not in h_acc:
            raise ValueError(f"h_acc is missing field {f!r}")
        want = tuple(getattr(gmap, f).shape)
        got = tuple(h_acc[f].shape)
        if got != want:
            raise ValueError(f"h_acc[{f!r}] has shape {list(got)}, the map's {f} has {list(want)}")
        h = h_acc[f]
        if not torch.isfinite(h).all() or not bool((h > 0).all()):
            raise ValueError(f"h_acc[{f!r}] must be positive and finite (it includes lambda)")
    if acquired is not None:
        if acquired.ndim != 3 or acquired.shape[1:] != (4, 4):
            raise ValueError(f"acquired must be poses [A, 4, 4], got {list(acquired.shape)}")
        if acquired.shape[0]:
            check_pose(acquired, "acquired")
    if current is not None:
        if (
            isinstance(current, bool)
            or int(current) != current
            or not (0 <= int(current) < candidates.shape[0])
        ):
            raise ValueError(
                f"current must be an index into candidates (0..{candidates.shape[0] - 1}), "
                f"got {current!r}"
            )
    if current_pose is not None:
        if current_pose.shape != (4, 4):
            raise ValueError(f"current_pose must be [4, 4], got {list(current_pose.shape)}")
        check_pose(current_pose, "current_pose")
    if config.embodied_k is not None and current is None and current_pose is None:
        raise ValueError("config.embodied_k needs the current view: pass current or current_pose")


# ----------------------------------------------------------------------------- helpers
def _generator(seed: int, event: int, salt: int) -> torch.Generator:
    return torch.Generator().manual_seed(
        (int(seed) * 1_000_003 + int(event) * 7919 + salt) % (2**63 - 1)
    )


def _pool_radius(candidates: Tensor, aim: Tensor) -> float:
    return max(float((candidates[:, :3, 3] - aim).norm(dim=1).median()), 1e-6)


def eligible_candidates(
    candidates: Tensor,
    *,
    embodied_k: int | None,
    current: int | None = None,
    current_pose: Tensor | None = None,
    rot_weight: float = 1.0,
) -> list[int]:
    """Indices of the eligible candidates: all, or the K nearest to the current view.

    The current view (``current``) is excluded; distances are ``se3.pose_distance`` with
    ``rot_weight``; ties go to the lower index.
    """
    d = candidates.shape[0]
    if embodied_k is None:
        return list(range(d))
    ref = candidates[int(current)] if current is not None else current_pose
    assert ref is not None
    dist = pose_distance(
        candidates.detach(), ref.detach().to(candidates.dtype).expand_as(candidates), rot_weight
    )
    dist = dist.to(torch.float64)
    if current is not None:
        dist[int(current)] = math.inf
    order = torch.sort(dist, stable=True).indices.tolist()
    k = min(int(embodied_k), d - (1 if current is not None else 0))
    return sorted(order[: max(k, 0)]) if k > 0 else []


def eig_scores(
    gmap: GaussianMap,
    h_acc: Mapping[str, Tensor],
    poses: Tensor,
    intrinsics: Intrinsics,
    *,
    fields: tuple[str, ...] = FIELD_NAMES,
    background: Tensor | None = None,
) -> Tensor:
    """phi(v) = sum_q log(1 + H_v,qq / Hhat_qq) for every pose [V, 4, 4] -> [V].

    One exact ``fisher_diag`` pass per view, only for the blocks in ``fields``; 1 / Hhat is
    formed once and each view's Fisher is turned into its log1p-sum in place (no copies).
    """
    g = gmap.detach()
    inv = {f: h_acc[f].detach().to(g.dtype).reciprocal() for f in fields}
    out = torch.empty(poses.shape[0], dtype=torch.float64)
    with torch.no_grad():
        for i, pose in enumerate(poses.detach().to(g.dtype)):
            h = fisher_diag(
                g, Camera(c2w=pose, intrinsics=intrinsics), fields=fields, background=background
            )
            total = 0.0
            for f in fields:
                total += float(h[f].mul_(inv[f]).log1p_().sum(dtype=torch.float64))
            out[i] = total
    return out


def _argmax_first(values: Tensor) -> int:
    """Index of the largest value, the lowest index on ties (NaN never wins)."""
    v = torch.nan_to_num(values.to(torch.float64), nan=-math.inf)
    return int(torch.argmax(v))


# ----------------------------------------------------------------------------- select
def select(
    method: str,
    gmap: GaussianMap,
    h_acc: Mapping[str, Tensor],
    candidates: Tensor,
    intrinsics: Intrinsics,
    *,
    config: SelectConfig | None = None,
    acquired: Tensor | None = None,
    current: int | None = None,
    current_pose: Tensor | None = None,
    state: dict[str, Any] | None = None,
) -> Selection:
    """Choose the next view among ``candidates`` with ``method`` (see the module docstring).

    Args:
        method: one of ``METHODS``.
        gmap: the current map.
        h_acc: accumulated information Hhat per field, including lambda (the map's shapes).
        candidates: the pool, camera-to-world poses [D, 4, 4] (OpenCV axes).
        intrinsics: shared by every candidate.
        config: settings (None: defaults).
        acquired: poses of the views acquired so far [A, 4, 4] (COVER's bins; A scales the
            proxy's typical Fisher).
        current: index of the current view in ``candidates`` (embodied mode).
        current_pose: the current pose [4, 4] when it is not in the pool (embodied mode).
        state: the previous ``Selection.state`` (warm start), or None.

    Raises:
        ValueError: naming the argument, for an unknown method, an empty pool, a budget < 1,
            NaN poses, non-orthonormal rotations, h_acc not matching the map, embodied_k < 1.
    """
    t_start = time.perf_counter()
    config = config or SelectConfig()
    fields = tuple(config.fields) if config.fields is not None else FIELD_NAMES
    _validate(
        method, gmap, h_acc, candidates, intrinsics, acquired, current, current_pose, config, fields
    )
    state = dict(state or {})
    event = int(state.get("event", 0))
    dt = gmap.dtype
    pool = candidates.detach().to(dt)
    aim, _ = scene_center_radius(gmap.means)
    radius = _pool_radius(pool, aim)
    sc = config.scoring
    rot_weight = sc.rot_weight if sc.rot_weight is not None else radius
    eligible = eligible_candidates(
        pool,
        embodied_k=config.embodied_k,
        current=current,
        current_pose=current_pose,
        rot_weight=rot_weight,
    )
    if not eligible:
        raise ValueError("candidates: no eligible candidate (the pool holds only the current view)")
    elig_t = torch.as_tensor(eligible, dtype=torch.long)
    lat = {k: 0.0 for k in STAGES}
    bg = (
        None
        if config.fisher_background is None
        else torch.tensor(config.fisher_background, dtype=dt)
    )
    details: dict[str, Any] = {}
    shortlist: list[int] = []
    scores: dict[int, float] = {}
    anchor_c2w: Tensor | None = None
    psi_trace: list[float] = []
    new_state: dict[str, Any] = {"event": event + 1}

    if method == "random":
        g = _generator(config.seed, event, 1)
        index = eligible[int(torch.randint(len(eligible), (1,), generator=g))]
    elif method == "fisherrf":
        t0 = time.perf_counter()
        phi = eig_scores(gmap, h_acc, pool[elig_t], intrinsics, fields=fields, background=bg)
        lat["scoring"] = (time.perf_counter() - t0) * 1e3
        scores = {v: float(p) for v, p in zip(eligible, phi)}
        index = eligible[_argmax_first(phi)]
    elif method == "cover":
        t0 = time.perf_counter()
        acq = acquired if acquired is not None else torch.zeros(0, 4, 4, dtype=dt)
        cs = cover_scores(
            gmap,
            pool[elig_t],
            intrinsics,
            acq.to(dt),
            num_bins=config.cover_bins,
            resolution=config.cover_resolution,
            near=sc.near,
        )
        lat["scoring"] = (time.perf_counter() - t0) * 1e3
        scores = {v: float(s) for v, s in zip(eligible, cs)}
        index = eligible[_argmax_first(-cs)]
    else:
        # ---- anchor
        t0 = time.perf_counter()
        envelope = (
            PoolEnvelope.from_pool(pool, aim, config.anchor.envelope_margin)
            if config.anchor.envelope
            else None
        )
        warm = state.get("anchor_c2w") if config.anchor.warm_start else None
        if warm is not None and (
            not isinstance(warm, Tensor) or warm.shape != (4, 4) or not torch.isfinite(warm).all()
        ):
            warm = None
        num_acq = int(acquired.shape[0]) if acquired is not None else 1
        typical = state.get("typical_fisher")
        if config.anchor.typical_fisher == "start_view" and typical is None:
            # one Fisher pass at a typical view: the last acquired one (else the first
            # eligible candidate); cached in state for the next events
            ref = (
                acquired[-1].to(dt)
                if acquired is not None and acquired.shape[0]
                else pool[eligible[0]]
            )
            cam = Camera(c2w=ref, intrinsics=intrinsics)
            with torch.no_grad():
                hv = fisher_diag(gmap.detach(), cam, fields=fields, background=bg)
            typical = typical_fisher_from_views([hv], fields)
        if config.anchor.typical_fisher == "start_view":
            new_state["typical_fisher"] = typical
        else:
            typical = None
        res = optimize_anchor(
            gmap,
            dict(h_acc),
            pool[elig_t],
            intrinsics,
            config=config.anchor,
            fields=fields,
            num_acquired=num_acq,
            envelope=envelope,
            warm_c2w=warm,
            typical=typical,
            generator=_generator(config.seed, event, 2),
            acquired=acquired.to(dt) if acquired is not None else None,
        )
        anchor_c2w = res.c2w
        psi_trace = list(res.psi_trace)
        new_state["anchor_c2w"] = anchor_c2w.clone()
        lat["anchor"] = (time.perf_counter() - t0) * 1e3
        details.update(
            psi_evaluations=res.evaluations,
            anchor_starts=[eligible[i] for i in res.extra.get("start_indices", [])],
            proxy_samples=res.extra.get("proxy_samples"),
        )
        if res.pool_psi is not None:
            details["pool_proxy_psi"] = {v: float(p) for v, p in zip(eligible, res.pool_psi)}
        # ---- scoring: support samples, M, B
        t0 = time.perf_counter()
        n_short = min(int(config.shortlist_size), len(eligible))
        if config.shortlist == "knearest":
            dist = pose_distance(
                pool[elig_t], anchor_c2w.expand(len(eligible), 4, 4), rot_weight
            ).to(torch.float64)
            order = torch.sort(dist, stable=True).indices.tolist()[:n_short]
            lat["scoring"] = (time.perf_counter() - t0) * 1e3
            t1 = time.perf_counter()
            shortlist = [eligible[i] for i in order]
            scores = {eligible[i]: float(dist[i]) for i in order}
            lat["leverage"] = (time.perf_counter() - t1) * 1e3
        else:
            x = support_samples(
                gmap.means,
                anchor_c2w,
                intrinsics,
                opacities=gmap.opacities.detach(),
                grid=sc.grid,
                ray_samples=sc.ray_samples,
                ray_min_fraction=sc.ray_min_fraction,
                min_opacity=sc.min_opacity,
                near=sc.near,
                max_samples=sc.max_samples,
                generator=_generator(config.seed, event, 3),
            )
            sigma_p = sc.sigma_p if sc.sigma_p is not None else 0.5 * radius
            # the acquired views' rows (scored like the candidates, rows are independent)
            # condition the leverage shortlist: one coverage matrix for both
            n_elig = len(eligible)
            rows = pool[elig_t]
            if (
                config.shortlist == "leverage"
                and sc.condition_on_acquired
                and acquired is not None
                and acquired.shape[0]
            ):
                rows = torch.cat([rows, acquired.detach().to(dt)])
            cov = coverage_matrix(
                x,
                rows,
                anchor_c2w,
                intrinsics,
                sigma_p=sigma_p,
                gamma=sc.gamma,
                eps=sc.eps * radius,
                near=sc.near,
            )
            pi = jl_projection(x.shape[0], sc.jl_dim, seed=config.seed, dtype=dt, device=x.device)
            b_all = cov.m @ pi
            b, prior = b_all[:n_elig], b_all[n_elig:]
            lat["scoring"] = (time.perf_counter() - t0) * 1e3
            details["support_samples"] = int(x.shape[0])
            details["rho"] = {v: float(r) for v, r in zip(eligible, cov.rho[:n_elig])}
            # ---- shortlist
            t1 = time.perf_counter()
            bmax = float((b.to(torch.float64) ** 2).sum(1).max())
            ridge = sc.ridge if sc.ridge_absolute else sc.ridge * max(bmax, 1e-30)
            if config.shortlist == "leverage":
                loc, gains = greedy_ridge_leverage_gains(b, n_short, ridge, prior)
            elif config.shortlist == "topnorm":
                loc = topnorm_shortlist(b, n_short)
                norms = b.to(torch.float64).norm(dim=1)
                gains = [float(norms[i]) for i in loc]
            else:
                loc = online_ridge_leverage(
                    b,
                    n_short,
                    ridge,
                    generator=_generator(config.seed, event, 4),
                    oversample=sc.online_oversample,
                )
                gains = [float("nan")] * len(loc)
            shortlist = [eligible[i] for i in loc]
            scores = {v: g for v, g in zip(shortlist, gains)}
            lat["leverage"] = (time.perf_counter() - t1) * 1e3
        if method == "agile":
            index = shortlist[0]
        else:
            t2 = time.perf_counter()
            sl = torch.as_tensor(shortlist, dtype=torch.long)
            phi = eig_scores(gmap, h_acc, pool[sl], intrinsics, fields=fields, background=bg)
            lat["rerank"] = (time.perf_counter() - t2) * 1e3
            details["shortlist_scores"] = scores
            scores = {v: float(p) for v, p in zip(shortlist, phi)}
            index = shortlist[_argmax_first(phi)]
    lat["total"] = (time.perf_counter() - t_start) * 1e3
    return Selection(
        method=method,
        index=int(index),
        shortlist=shortlist,
        anchor_c2w=anchor_c2w,
        psi_trace=psi_trace,
        scores=scores,
        eligible=eligible,
        latency_ms=lat,
        state=new_state,
        details=details,
    )
