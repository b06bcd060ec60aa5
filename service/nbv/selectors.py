"""One entry point for every next-best-view method: ``select``.

The methods (paper sections 3-5 and its baselines) are registered by name in
:mod:`agilegs.service.nbv.methods`, one module each; all select on the same map, Hhat and
pool. ``select`` validates its inputs into one :class:`SelectInputs` (a caller that
validated them already, as the service does once per setting, builds the
:class:`SelectInputs` itself and selects through ``select_from``), works out what every method
shares (the eligible candidates, the pool's radius, the event counter of the warm state),
runs the method and times it.

Embodied mode (``SelectConfig.embodied_k = K``): only the K candidates nearest the current
view (``current`` index, which is itself excluded, or ``current_pose``) are eligible; nearest
by camera centre (``embodied_metric="position"``, COVER's protocol: a KD-tree query of the
remaining frames' origins around the last acquired view's) or by the SE(3) distance
``se3.pose_distance`` (``"se3"``).

Every random choice (random pick, importance sampling of the proxy, support samples, online
sampling) is drawn from generators seeded with ``SelectConfig.seed`` and the event counter
kept in ``state``, so the same seed and state give the same selection. The JL matrix depends
on the seed only: it is fixed across events.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from agilegs.config.selection import (
    FIELD_NAMES,
    SHORTLISTS,
    AnchorConfig,
    ScoringConfig,
    SelectConfig,
    for_method,
)
from agilegs.config.types import validate_config

from .camera import Intrinsics, check_pose
from .candidates import pool_radius, scene_center_radius
from .errors import InputError
from .gaussians import GaussianMap
from .information import eig_scores
from .methods.base import STAGES, SelectionContext, get_method, method_names
from .se3 import pose_distance

__all__ = [
    "METHODS",
    "SHORTLISTS",
    "STAGES",
    "AnchorConfig",
    "ScoringConfig",
    "SelectConfig",
    "SelectInputs",
    "Selection",
    "eig_scores",
    "eligible_candidates",
    "select",
    "select_from",
    "state_to",
]


def state_to(device: torch.device | str, value: Any) -> Any:
    """``value`` (a warm state, Hhat: tensors in dicts, lists and tuples) with every tensor on
    ``device``; what is not a tensor is kept as it is."""
    if isinstance(value, Tensor):
        return value.to(device)
    if isinstance(value, dict):
        return {k: state_to(device, v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(state_to(device, v) for v in value)
    return value

METHODS: tuple[str, ...] = method_names()


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
        chosen_information: the diagonal Fisher of the chosen view (per block of
            ``config.fields``, rendered on ``config.fisher_background``) where the method
            computed it while scoring (full_eig, agile_plus), else None: what acquiring the
            view adds to Hhat, without another pass.
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
    chosen_information: dict[str, Tensor] | None = None


# ----------------------------------------------------------------------------- validation
def _validate(
    gmap: GaussianMap,
    h_acc: Mapping[str, Tensor],
    candidates: Tensor,
    intrinsics: Intrinsics,
    acquired: Tensor | None,
    current: int | None,
    current_pose: Tensor | None,
    config: SelectConfig,
    fields: tuple[str, ...],
    uses_map: bool = True,
) -> None:
    if not isinstance(gmap, GaussianMap):
        raise TypeError(f"gmap must be a GaussianMap, got {type(gmap).__name__}")
    if gmap.num_gaussians == 0 and uses_map:
        raise InputError("gmap", "gmap has no Gaussians")
    if not isinstance(intrinsics, Intrinsics):
        raise TypeError(f"intrinsics must be an Intrinsics, got {type(intrinsics).__name__}")
    if not isinstance(candidates, Tensor) or candidates.ndim != 3 or candidates.shape[1:] != (4, 4):
        shape = list(getattr(candidates, "shape", [])) or type(candidates).__name__
        raise InputError("candidates", f"candidates must be a tensor of poses [D, 4, 4], got "
                                       f"{shape}")
    if candidates.shape[0] == 0:
        raise InputError("candidates", "candidates is empty: the pool needs at least one pose")
    check_pose(candidates, "candidates")
    if not isinstance(h_acc, Mapping):
        raise InputError("h_acc", f"h_acc must be a dict of per-field tensors, got "
                                  f"{type(h_acc).__name__}")
    for f in fields:
        if f not in h_acc:
            raise InputError("h_acc", f"h_acc is missing field {f!r}")
        want = tuple(getattr(gmap, f).shape)
        got = tuple(h_acc[f].shape)
        if got != want:
            raise InputError("h_acc", f"h_acc[{f!r}] has shape {list(got)}, the map's {f} has "
                                      f"{list(want)}")
        h = h_acc[f]
        if not torch.isfinite(h).all() or not bool((h > 0).all()):
            raise InputError("h_acc", f"h_acc[{f!r}] must be positive and finite (it includes "
                                      "lambda)")
    if acquired is not None:
        if acquired.ndim != 3 or acquired.shape[1:] != (4, 4):
            raise InputError("acquired", f"acquired must be poses [A, 4, 4], got "
                                         f"{list(acquired.shape)}")
        if acquired.shape[0]:
            check_pose(acquired, "acquired")
    if current is not None:
        if (
            isinstance(current, bool)
            or int(current) != current
            or not (0 <= int(current) < candidates.shape[0])
        ):
            raise InputError("current", f"current must be an index into candidates "
                                        f"(0..{candidates.shape[0] - 1}), got {current!r}")
    if current_pose is not None:
        if current_pose.shape != (4, 4):
            raise InputError("current_pose", f"current_pose must be [4, 4], got "
                                             f"{list(current_pose.shape)}")
        check_pose(current_pose, "current_pose")
    if config.embodied_k is not None and current is None and current_pose is None:
        raise InputError("current", "config.embodied_k needs the current view: pass current or "
                                    "current_pose")


def eligible_candidates(
    candidates: Tensor,
    *,
    embodied_k: int | None,
    current: int | None = None,
    current_pose: Tensor | None = None,
    rot_weight: float = 1.0,
    metric: str = "position",
) -> list[int]:
    """Indices of the eligible candidates: all, or the K nearest to the current view.

    The current view (``current``) is excluded; distances are between camera centres
    (``metric="position"``) or ``se3.pose_distance`` with ``rot_weight`` (``"se3"``); ties
    go to the lower index.
    """
    d = candidates.shape[0]
    if embodied_k is None:
        return list(range(d))
    ref = candidates[int(current)] if current is not None else current_pose
    assert ref is not None
    ref = ref.detach().to(candidates.dtype)
    if metric == "position":
        dist = (candidates.detach()[:, :3, 3] - ref[:3, 3]).norm(dim=1)
    elif metric == "se3":
        dist = pose_distance(candidates.detach(), ref.expand_as(candidates), rot_weight)
    else:
        raise ValueError(f"metric must be 'position' or 'se3', got {metric!r}")
    dist = dist.to(torch.float64)
    if current is not None:
        dist[int(current)] = math.inf
    order = torch.sort(dist, stable=True).indices.tolist()
    k = min(int(embodied_k), d - (1 if current is not None else 0))
    return sorted(order[: max(k, 0)]) if k > 0 else []


# ----------------------------------------------------------------------------- select
@dataclass(frozen=True, eq=False)
class SelectInputs:
    """What one selection selects on: :func:`select`'s arguments of the same names but the
    warm state (``config`` not None).

    :meth:`checked` validates every field (what :func:`select` does); without it the fields
    are taken as valid: ``config`` a validated :class:`SelectConfig` and everything
    :meth:`checked` checks (a non-empty map, Hhat positive and of the map's shapes, a
    non-empty pool of proper poses, ``current`` an index into it, a current view in embodied
    mode, ``lam`` > 0), as the service does once per setting (a pool when it arrives, Hhat as
    it is kept up).
    """

    method: str
    gmap: GaussianMap
    h_acc: Mapping[str, Tensor]
    candidates: Tensor
    intrinsics: Intrinsics
    config: SelectConfig
    acquired: Tensor | None = None
    current: int | None = None
    current_pose: Tensor | None = None
    lam: float | None = None
    targets: Tensor | None = None

    @property
    def fields(self) -> tuple[str, ...]:
        """The parameter blocks selected on (``config.fields``, else all)."""
        return tuple(self.config.fields) if self.config.fields is not None else FIELD_NAMES

    def checked(self) -> SelectInputs:
        """These inputs validated (:func:`select`'s checks and errors), ``config`` as its
        validated copy."""
        impl = get_method(self.method)
        config = validate_config(SelectConfig, self.config)
        fields = tuple(config.fields) if config.fields is not None else FIELD_NAMES
        _validate(self.gmap, self.h_acc, self.candidates, self.intrinsics, self.acquired,
                  self.current, self.current_pose, config, fields,
                  getattr(impl, "uses_map", True))
        lam = self.lam
        if lam is not None and not (isinstance(lam, int | float) and math.isfinite(lam)
                                    and lam > 0):
            raise InputError("lam", f"lam must be a positive finite number, got {lam!r}")
        t = self.targets
        if t is not None:
            if not isinstance(t, Tensor) or t.ndim != 3 or t.shape[1:] != (4, 4) or not len(t):
                raise InputError("targets", "targets must be a tensor of poses [T, 4, 4], T >= 1")
            check_pose(t, "targets")
        return dataclasses.replace(self, config=config)


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
    lam: float | None = None,
    targets: Tensor | None = None,
) -> Selection:
    """Choose the next view among ``candidates`` with ``method``.

    Args:
        method: a registered method name (``METHODS``).
        gmap: the current map.
        h_acc: accumulated information Hhat per field, including lambda (the map's shapes).
        candidates: the pool, camera-to-world poses [D, 4, 4] (OpenCV axes).
        intrinsics: shared by every candidate.
        config: settings (None: defaults).
        acquired: poses of the views acquired so far [A, 4, 4] (COVER's bins; the anchor's
            fitted proxy).
        current: index of the current view in ``candidates`` (embodied mode).
        current_pose: the current pose [4, 4] when it is not in the pool (embodied mode).
        state: the previous ``Selection.state`` (warm start), or None.
        lam: the lambda included in ``h_acc`` (Hhat = lambda + sum of the views' Fisher);
            the anchor's proxy separates the views' information from it. None: estimated
            as each parameter slot's minimum over Gaussians (exact only when some Gaussian
            is seen by no acquired view).
        targets: the target views [T, 4, 4] of ``config.objective = "target"`` (None: the
            pool); ignored by the ``eig`` objective.

    Raises:
        ValueError: naming the argument, for an unknown method, an empty pool, a budget < 1,
            NaN poses, non-orthonormal rotations, h_acc not matching the map, embodied_k < 1.
    """
    started = time.perf_counter()
    inputs = SelectInputs(method, gmap, h_acc, candidates, intrinsics,
                          config if config is not None else SelectConfig(), acquired, current,
                          current_pose, lam, targets)
    return select_from(inputs.checked(), state=state, started=started)


def select_from(inputs: SelectInputs, *, state: dict[str, Any] | None = None,
                started: float | None = None) -> Selection:
    """Choose the next view with ``inputs`` (taken as valid: see :class:`SelectInputs`).

    ``state``: the previous ``Selection.state`` (warm start), or None. ``started``: the
    ``time.perf_counter()`` the call's total latency counts from (None: now). Raises
    :class:`~agilegs.service.nbv.errors.InputError` only when no candidate is eligible.
    """
    t_start = time.perf_counter() if started is None else started
    impl = get_method(inputs.method)
    config = for_method(inputs.config, inputs.method)
    state = dict(state or {})
    event = int(state.get("event", 0))
    gmap = inputs.gmap
    dt = gmap.dtype
    pool = inputs.candidates.detach().to(dt)
    # a method that reads no map (spread) may select before the map has a Gaussian
    aim = (scene_center_radius(gmap.means)[0] if gmap.num_gaussians
           else pool[:, :3, 3].mean(0))
    radius = pool_radius(pool, aim)
    sc = config.scoring
    rot_weight = sc.rot_weight if sc.rot_weight is not None else radius
    eligible = eligible_candidates(
        pool,
        embodied_k=config.embodied_k,
        current=inputs.current,
        current_pose=inputs.current_pose,
        rot_weight=rot_weight,
        metric=config.embodied_metric,
    )
    if not eligible:
        raise InputError("candidates", "candidates: no eligible candidate (the pool holds only "
                                       "the current view)")
    bg = (
        None
        if config.fisher_background is None
        else torch.tensor(config.fisher_background, dtype=dt)
    )
    ctx = SelectionContext(
        gmap=gmap, h_acc=inputs.h_acc, pool=pool, intrinsics=inputs.intrinsics, config=config,
        fields=inputs.fields, eligible=eligible, acquired=inputs.acquired, state=state,
        event=event, aim=aim, radius=radius, rot_weight=rot_weight, background=bg,
        lam=inputs.lam,
        targets=(None if inputs.targets is None
                 else inputs.targets.detach().to(device=pool.device, dtype=dt)),
    )
    res = impl(ctx)
    lat = {k: 0.0 for k in STAGES}
    lat.update(res.latency_ms)
    lat["total"] = (time.perf_counter() - t_start) * 1e3
    return Selection(
        method=inputs.method,
        index=int(res.index),
        shortlist=res.shortlist,
        anchor_c2w=res.anchor_c2w,
        psi_trace=res.psi_trace,
        scores=res.scores,
        eligible=eligible,
        latency_ms=lat,
        state={"event": event + 1, **res.state},
        details=res.details,
        chosen_information=res.chosen_information,
    )
