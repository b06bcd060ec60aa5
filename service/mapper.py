"""Incremental 3D Gaussian Splatting training: the mapper of a map session.

The mapper owns the Gaussians being trained (leaf tensors with ``requires_grad``), an Adam
optimiser with one parameter group per field, the acquired views and the densification
statistics. It follows the reference 3DGS recipe (Kerbl et al. 2023, ``train.py`` and
``gaussian_model.py``), made incremental:

- a new view (:meth:`Mapper.add_view`) never resets the map: it is appended to the views that
  :meth:`Mapper.step` samples from (uniformly, with a seeded generator); with a depth map (and
  ``MapperConfig.extend_from_depth``) the pixels the current map does not cover (rendered
  alpha below ``extend_alpha_threshold``) are back-projected into new Gaussians;
- loss ``(1 - λ) L1 + λ (1 - SSIM)`` on ``render(...).rgb`` (3DGS, λ = ``lambda_dssim``), plus
  ``lambda_depth`` times the L1 of the rendered expected depth on pixels with valid depth when
  the view has one;
- densification every ``densify_every`` steps from ``densify_from`` to ``densify_until``: the
  screen-space mean gradient (pixel gradient times (W/2, H/2), i.e. the NDC gradient of the
  reference) is averaged over the steps where a Gaussian was visible (radius > 0); Gaussians with
  an average ≥ ``densify_grad_threshold`` are cloned when small (max scale ≤ ``percent_dense`` ×
  extent) and split into ``split_samples`` children (positions sampled from the Gaussian,
  scales divided by ``split_scale_divisor``) when large; then Gaussians with opacity below
  ``prune_opacity`` are pruned, and, after ``prune_large_from`` steps, those with a screen radius
  above ``max_screen_radius`` pixels or a world scale above ``max_world_scale`` × extent;
- optional opacity reset (every ``opacity_reset_every`` steps, opacities clamped to
  ``opacity_reset_value``, their Adam moments zeroed), optional SH degree schedule;
- position learning rate decays exponentially from ``lr_means`` to ``lr_means_final``
  (× scene extent) over ``lr_means_steps`` steps.

Topology changes (densify, prune, extension from depth, initialisation, a replaced map) are
reported to every callable in :attr:`Mapper.on_topology_change` as a :class:`TopologyChange`
whose ``src`` [N_new] says where each new Gaussian came from:

    new Gaussian j is a copy (kept, clone or split child) of old Gaussian ``src[j]``,
    or brand new when ``src[j] == -1``.

:func:`remap_per_gaussian` carries per-Gaussian state (e.g. the accumulated information Ĥ)
across such a change. Adam moments are carried for the Gaussians that survive as themselves
(``TopologyChange.identity``) and start at zero for clones, split children and new Gaussians
(as in the reference).
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import torch
from torch import Tensor

from agilegs.service.data.loaders import View
from agilegs.service.nbv.camera import Camera
from agilegs.service.nbv.gaussians import GaussianMap
from agilegs.service.nbv.rasterize import quat_to_rotmat, render
from agilegs.service.quality import ssim_loss

log = logging.getLogger(__name__)

__all__ = [
    "MapperConfig",
    "Mapper",
    "TopologyChange",
    "remap_per_gaussian",
    "backproject_depth",
    "nearest_neighbour_scales",
]

_PARAM_KEYS: tuple[str, ...] = (
    "means",
    "log_scales",
    "quats",
    "opacity_logits",
    "sh_dc",
    "sh_rest",
)


@dataclass
class MapperConfig:
    """Training settings of :class:`Mapper` (3DGS defaults unless said otherwise).

    Args:
        lr_means: initial Adam learning rate of the means, times the scene extent (1.6e-4).
        lr_means_final: final means learning rate, times the scene extent (1.6e-6).
        lr_means_steps: steps of the exponential decay from ``lr_means`` to ``lr_means_final``
            (30000); the rate stays at the final value afterwards.
        lr_log_scales: learning rate of the log-scales (5e-3).
        lr_quats: learning rate of the quaternions (1e-3).
        lr_opacity: learning rate of the opacity logits (5e-2).
        lr_sh_dc: learning rate of the SH DC coefficients (2.5e-3).
        lr_sh_rest: learning rate of the higher SH bands (2.5e-3 / 20).
        adam_eps: Adam epsilon (1e-15, as the reference).
        lambda_dssim: weight λ of D-SSIM in ``(1 - λ) L1 + λ (1 - SSIM)`` (0.2).
        lambda_depth: weight of the depth L1 for views with depth (0.1; 0 disables it).
        scene_extent: scene radius used to scale ``lr_means``, ``percent_dense`` and
            ``max_world_scale``. None: estimated at the first :meth:`Mapper.step` as 1.1 × the
            largest distance of an acquired camera from their centroid (the reference's rule)
            when at least two views are far apart, else 1.1 × the half diagonal of the
            Gaussians' 2-98 percentile box. Set it explicitly when known.
        sh_degree: SH degree of Gaussians the mapper creates from points or depth (3); a map
            passed to the constructor keeps its own degree.
        sh_degree_interval: the active SH degree grows by one every this many steps, from 0 up
            to the map's degree (1000); None trains every band from the start.
        densify: enable densification and pruning (True).
        densify_from: first step at which to densify (100; the reference uses 500).
        densify_every: densify every this many steps (100).
        densify_until: last step at which to densify or reset opacity (15000; None: forever).
        densify_grad_threshold: average NDC-space mean-gradient norm that triggers
            densification (2e-4).
        percent_dense: clone when max scale ≤ percent_dense × extent, else split (0.01).
        split_samples: children of a split Gaussian (2).
        split_scale_divisor: children's scales are the parent's divided by this (1.6 =
            0.8 × split_samples, the reference).
        prune_opacity: prune Gaussians with opacity below this (0.005).
        prune_large_from: after this step also prune Gaussians larger than
            ``max_screen_radius`` pixels or ``max_world_scale`` × extent (3000, the reference
            does it after the first opacity reset; None: never).
        max_screen_radius: screen-radius threshold in pixels of the large-Gaussian pruning (20).
        max_world_scale: world-scale threshold (× extent) of the large-Gaussian pruning (0.1).
        opacity_reset_every: reset opacities every this many steps (3000; None: never).
        opacity_reset_value: opacities are clamped to at most this at a reset (0.01).
        max_gaussians: cap on the number of Gaussians: densification keeps the candidates with
            the largest gradients that fit, and extension from depth stops at the cap
            (1_000_000; None: no cap).
        background: RGB in [0, 1] composited behind the Gaussians in training renders
            (black); use the colour the reference images were composited on.
        init_opacity: opacity of Gaussians created from points or depth (0.1).
        init_stride: pixel stride of the back-projection grid of depth maps (4).
        init_max_points: at most this many points per back-projection call, randomly
            subsampled with the seeded generator (50000; None: all).
        extend_from_depth: :meth:`Mapper.add_view` with a depth map adds Gaussians where the
            current map's rendered alpha is below ``extend_alpha_threshold`` (True); on an
            empty map this initialises it.
        extend_alpha_threshold: alpha under which a pixel counts as not yet covered (0.5).
        seed: seed of the view sampler, the split sampler and point subsampling (0).
        tile_size: rasterizer tile edge in pixels (8).
    """

    lr_means: float = 1.6e-4
    lr_means_final: float = 1.6e-6
    lr_means_steps: int = 30_000
    lr_log_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_opacity: float = 5e-2
    lr_sh_dc: float = 2.5e-3
    lr_sh_rest: float = 2.5e-3 / 20
    adam_eps: float = 1e-15
    lambda_dssim: float = 0.2
    lambda_depth: float = 0.1
    scene_extent: float | None = None
    sh_degree: int = 3
    sh_degree_interval: int | None = 1000
    densify: bool = True
    densify_from: int = 100
    densify_every: int = 100
    densify_until: int | None = 15_000
    densify_grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    split_samples: int = 2
    split_scale_divisor: float = 1.6
    prune_opacity: float = 0.005
    prune_large_from: int | None = 3000
    max_screen_radius: float = 20.0
    max_world_scale: float = 0.1
    opacity_reset_every: int | None = 3000
    opacity_reset_value: float = 0.01
    max_gaussians: int | None = 1_000_000
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    init_opacity: float = 0.1
    init_stride: int = 4
    init_max_points: int | None = 50_000
    extend_from_depth: bool = True
    extend_alpha_threshold: float = 0.5
    seed: int = 0
    tile_size: int = 8

    def __post_init__(self) -> None:
        positive = (
            "lr_means",
            "lr_means_final",
            "lr_log_scales",
            "lr_quats",
            "lr_opacity",
            "lr_sh_dc",
            "lr_sh_rest",
            "adam_eps",
            "split_scale_divisor",
            "max_screen_radius",
            "max_world_scale",
            "percent_dense",
        )
        for name in positive:
            v = float(getattr(self, name))
            if not (v > 0 and math.isfinite(v)):
                raise ValueError(f"MapperConfig.{name} must be positive and finite, got {v}")
        for name in ("lambda_dssim", "extend_alpha_threshold"):
            v = float(getattr(self, name))
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"MapperConfig.{name} must be in [0, 1], got {v}")
        for name in ("lambda_depth", "densify_grad_threshold", "prune_opacity"):
            v = float(getattr(self, name))
            if not (v >= 0 and math.isfinite(v)):
                raise ValueError(f"MapperConfig.{name} must be >= 0 and finite, got {v}")
        if not 0.0 < self.opacity_reset_value < 1.0:
            raise ValueError(
                "MapperConfig.opacity_reset_value must be in (0, 1), got "
                f"{self.opacity_reset_value}"
            )
        if not 0.0 < self.init_opacity < 1.0:
            raise ValueError(
                f"MapperConfig.init_opacity must be in (0, 1), got {self.init_opacity}"
            )
        for name in (
            "lr_means_steps",
            "densify_every",
            "split_samples",
            "init_stride",
            "tile_size",
        ):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"MapperConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.split_samples < 2:
            raise ValueError(f"MapperConfig.split_samples must be >= 2, got {self.split_samples}")
        if self.densify_from < 0:
            raise ValueError(f"MapperConfig.densify_from must be >= 0, got {self.densify_from}")
        optional_pos = (
            "sh_degree_interval",
            "densify_until",
            "opacity_reset_every",
            "max_gaussians",
            "init_max_points",
        )
        for name in optional_pos:
            v = getattr(self, name)
            if v is not None and int(v) < 1:
                raise ValueError(f"MapperConfig.{name} must be >= 1 or None, got {v}")
        if self.prune_large_from is not None and self.prune_large_from < 0:
            raise ValueError(
                f"MapperConfig.prune_large_from must be >= 0 or None, got {self.prune_large_from}"
            )
        if not 0 <= self.sh_degree <= 3:
            raise ValueError(f"MapperConfig.sh_degree must be in 0..3, got {self.sh_degree}")
        if self.scene_extent is not None and not (
            self.scene_extent > 0 and math.isfinite(self.scene_extent)
        ):
            raise ValueError(
                f"MapperConfig.scene_extent must be positive and finite, got {self.scene_extent}"
            )
        bg = tuple(float(c) for c in self.background)
        if len(bg) != 3 or not all(0.0 <= c <= 1.0 for c in bg):
            raise ValueError(f"MapperConfig.background must be 3 values in [0, 1], got {bg}")
        self.background = (bg[0], bg[1], bg[2])

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class TopologyChange:
    """How the Gaussians after a change relate to those before.

    Attributes:
        src: LongTensor [N_new]: new Gaussian j is a copy of old Gaussian ``src[j]`` (kept,
            cloned, or a split child, which differs in position and scale), or brand new when
            ``src[j] == -1`` (from depth or points, or a replaced map).
        kept: BoolTensor [N_old]: old Gaussians that survive as themselves (not pruned, not
            replaced by split children); ``kept.sum()`` of the new ones have ``identity``.
        identity: BoolTensor [N_new]: new Gaussians that are an old Gaussian kept as itself
            (their Adam moments were carried; the others start from zero).
        num_old: N_old.
        num_new: N_new.
        reason: "densify" (clone/split then prune), "extend" (Gaussians added from a depth
            map), "init" (map initialised or replaced), or "replace" (``replace_gmap``).
        counts: e.g. {"cloned": ., "split": ., "pruned": ., "added": .}.
    """

    src: Tensor
    kept: Tensor
    identity: Tensor
    num_old: int
    num_new: int
    reason: str
    counts: dict[str, int] = field(default_factory=dict)


def remap_per_gaussian(
    values: Mapping[str, Tensor],
    src: Tensor,
    fill: float | Tensor | Mapping[str, float | Tensor] = 0.0,
) -> dict[str, Tensor]:
    """Carry per-Gaussian tensors across a topology change.

    Args:
        values: tensors whose first dimension is N_old (e.g. Ĥ per field: [N_old, ...]).
        src: LongTensor [N_new] from :class:`TopologyChange` (-1 for brand-new Gaussians).
        fill: value for brand-new Gaussians: a scalar, a tensor broadcastable to one row
            ``[...]``, or a mapping from key to either (keys it lacks are filled with 0).

    Returns:
        New dict with tensors [N_new, ...]: row j is ``values[k][src[j]]`` (so clones and split
        children copy their source) or ``fill`` where ``src[j] == -1``.
    """
    if src.ndim != 1 or src.dtype not in (torch.int64, torch.int32):
        raise ValueError(
            f"src must be an integer tensor [N_new], got {src.dtype} {list(src.shape)}"
        )
    out: dict[str, Tensor] = {}
    for k, v in values.items():
        n_old = v.shape[0] if v.ndim else 0
        if v.ndim == 0:
            raise ValueError(f"values[{k!r}] must have a Gaussian dimension first, got a scalar")
        s = src.to(v.device).long()
        if s.numel() and (int(s.max()) >= n_old or int(s.min()) < -1):
            raise ValueError(
                f"src indexes outside values[{k!r}] (N_old = {n_old}, src range "
                f"[{int(s.min())}, {int(s.max())}])"
            )
        f = fill.get(k, 0.0) if isinstance(fill, Mapping) else fill
        new = s < 0
        rows = v[s.clamp_min(0)] if n_old else v.new_zeros((s.numel(), *v.shape[1:]))
        if bool(new.any()):
            fv = torch.as_tensor(f, dtype=v.dtype, device=v.device)
            rows = rows.clone()
            rows[new] = fv.expand(int(new.sum()), *v.shape[1:]).to(v.dtype)
        out[k] = rows
    return out


# ----------------------------------------------------------------------------- geometry helpers
def backproject_depth(
    camera: Camera,
    depth: Tensor,
    image: Tensor | None = None,
    *,
    stride: int = 1,
    mask: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """World points of the pixels of a depth map (depth along the optical axis, camera z).

    Pixel (row v, column u) is back-projected through its centre (u + 0.5, v + 0.5):
    X_cam = ((u + 0.5 - cx) / fx · d, (v + 0.5 - cy) / fy · d, d), X = c2w X_cam.

    Args:
        camera: the view (OpenCV axes).
        depth: [H, W]; pixels with depth ≤ 0 or non-finite are skipped.
        image: colours [H, W, 3] in [0, 1] (None: grey 0.5).
        stride: take every ``stride``-th pixel in each direction (grid starting at
            ``stride // 2``).
        mask: optional bool [H, W]: only these pixels.

    Returns:
        (points [M, 3], colors [M, 3]) in the dtype/device of ``depth``.
    """
    h, w = camera.height, camera.width
    if depth.shape != (h, w):
        raise ValueError(
            f"depth must have shape [{h}, {w}] (the camera's), got {list(depth.shape)}"
        )
    if image is not None and image.shape != (h, w, 3):
        raise ValueError(f"image must have shape [{h}, {w}, 3], got {list(image.shape)}")
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    dt = depth.dtype if depth.dtype.is_floating_point else torch.float32
    dev = depth.device
    vs = torch.arange(stride // 2, h, stride, device=dev)
    us = torch.arange(stride // 2, w, stride, device=dev)
    vv, uu = torch.meshgrid(vs, us, indexing="ij")
    d = depth.to(dt)[vv, uu]
    ok = torch.isfinite(d) & (d > 0)
    if mask is not None:
        if mask.shape != (h, w):
            raise ValueError(f"mask must have shape [{h}, {w}], got {list(mask.shape)}")
        ok = ok & mask.to(dev)[vv, uu]
    d, uu, vv = d[ok], uu[ok], vv[ok]
    x = (uu.to(dt) + 0.5 - camera.cx) / camera.fx * d
    y = (vv.to(dt) + 0.5 - camera.cy) / camera.fy * d
    pc = torch.stack([x, y, d], dim=-1)
    c2w = camera.c2w.detach().to(device=dev, dtype=dt)
    pts = pc @ c2w[:3, :3].T + c2w[:3, 3]
    if image is None:
        cols = torch.full_like(pts, 0.5)
    else:
        cols = image.detach().to(device=dev, dtype=dt)[vv, uu]
    return pts, cols


def nearest_neighbour_scales(points: Tensor, k: int = 3, *, min_scale: float = 1e-7) -> Tensor:
    """Initial Gaussian scale per point [P]: sqrt of the mean squared distance to its ``k``
    nearest neighbours (the reference's ``distCUDA2`` rule), at least ``min_scale``."""
    p = points.shape[0]
    if p == 0:
        return points.new_zeros(0)
    if p == 1:
        return points.new_full((1,), 0.01)
    kk = min(k, p - 1)
    d2: Tensor
    try:
        from scipy.spatial import cKDTree

        arr = points.detach().cpu().double().numpy()
        dist, _ = cKDTree(arr).query(arr, k=kk + 1)
        d2 = torch.as_tensor(dist[:, 1:] ** 2, dtype=points.dtype, device=points.device)
    except ImportError:  # pragma: no cover - scipy comes with scikit-image
        chunk = max(1, (1 << 24) // p)
        parts = []
        pts = points.detach()
        for s in range(0, p, chunk):
            dd = torch.cdist(pts[s : s + chunk], pts).pow(2)
            dd[torch.arange(dd.shape[0]), torch.arange(s, s + dd.shape[0])] = float("inf")
            parts.append(dd.topk(kk, dim=1, largest=False).values)
        d2 = torch.cat(parts)
    return d2.reshape(p, -1).mean(dim=1).clamp_min(min_scale**2).sqrt()


# ----------------------------------------------------------------------------- the mapper
class Mapper:
    """Incremental 3DGS trainer (see the module docstring for the recipe).

    Args:
        gmap: initial Gaussians (copied), or None for an empty map to be initialised by
            :meth:`init_from_depth`, :meth:`init_from_points` or a first view with depth.
        config: training settings (default :class:`MapperConfig`).
        device: where training runs (default: ``gmap``'s device, else CPU).
        dtype: dtype of a map created from scratch (default float32; a given map keeps its own).

    Attributes:
        on_topology_change: callables invoked with a :class:`TopologyChange` after every change
            of the Gaussian set, once the mapper's tensors already hold the new set. They run
            under the mapper's lock and must not call back into training.
    """

    def __init__(
        self,
        gmap: GaussianMap | None = None,
        config: MapperConfig | None = None,
        *,
        device: torch.device | str | None = None,
        dtype: torch.dtype | None = None,
    ) -> None:
        if gmap is not None and not isinstance(gmap, GaussianMap):
            raise TypeError(f"gmap must be a GaussianMap or None, got {type(gmap).__name__}")
        if config is not None and not isinstance(config, MapperConfig):
            raise TypeError(f"config must be a MapperConfig, got {type(config).__name__}")
        self.config = config if config is not None else MapperConfig()
        if device is None:
            device = gmap.device if gmap is not None else "cpu"
        self.device = torch.device(device)
        if dtype is None:
            dtype = gmap.dtype if gmap is not None else torch.float32
        if not dtype.is_floating_point:
            raise ValueError(f"dtype must be a floating point dtype, got {dtype}")
        self.dtype = dtype
        self.on_topology_change: list[Callable[[TopologyChange], None]] = []
        self._lock = threading.RLock()
        self._views: list[View] = []
        self._num_steps = 0
        self._last_loss: float | None = None
        self._extent: float | None = self.config.scene_extent
        seed = int(self.config.seed)
        self._gen_views = torch.Generator().manual_seed(seed)
        self._gen_points = torch.Generator().manual_seed(seed + 1)
        self._gen_split = torch.Generator(device=self.device).manual_seed(seed + 2)
        self._bg = torch.tensor(self.config.background, dtype=dtype, device=self.device)
        self._sh_degree = gmap.sh_degree if gmap is not None else self.config.sh_degree
        self._params: dict[str, Tensor] = {}
        self._opt: torch.optim.Adam | None = None
        src_map = gmap if gmap is not None else self._empty_map()
        self._install(self._split_sh(src_map.detach().to(self.device, dtype)), carry=None)
        self._reset_stats()

    # ------------------------------------------------------------------ properties
    @property
    def gmap(self) -> GaussianMap:
        """A detached snapshot (copy) of the current Gaussians, all SH bands."""
        with self._lock:
            p = self._params
            sh = torch.cat([p["sh_dc"], p["sh_rest"]], dim=1)
            return GaussianMap(
                means=p["means"].detach().clone(),
                log_scales=p["log_scales"].detach().clone(),
                quats=p["quats"].detach().clone(),
                opacity_logits=p["opacity_logits"].detach().clone(),
                sh=sh.detach().clone(),
            )

    @property
    def num_gaussians(self) -> int:
        return int(self._params["means"].shape[0])

    @property
    def num_steps(self) -> int:
        """Training steps taken so far."""
        return self._num_steps

    @property
    def last_loss(self) -> float | None:
        """Loss of the last training step (None before the first)."""
        return self._last_loss

    @property
    def views(self) -> list[View]:
        """The acquired views (a new list; the views themselves are shared)."""
        with self._lock:
            return list(self._views)

    @property
    def num_views(self) -> int:
        return len(self._views)

    @property
    def scene_extent(self) -> float | None:
        """Scene extent in use (None until set or estimated at the first step)."""
        return self._extent

    @scene_extent.setter
    def scene_extent(self, value: float) -> None:
        v = float(value)
        if not (v > 0 and math.isfinite(v)):
            raise ValueError(f"scene_extent must be positive and finite, got {value}")
        with self._lock:
            self._extent = v
            self._update_lr()

    @property
    def active_sh_degree(self) -> int:
        iv = self.config.sh_degree_interval
        if iv is None:
            return self._sh_degree
        return min(self._sh_degree, self._num_steps // iv)

    @property
    def params(self) -> dict[str, Tensor]:
        """The live leaf tensors (means, log_scales, quats, opacity_logits, sh_dc, sh_rest).

        They are replaced at every topology change; do not keep references across steps."""
        return dict(self._params)

    # ------------------------------------------------------------------ views
    def add_view(
        self,
        camera: Camera,
        image: Tensor,
        depth: Tensor | None = None,
        *,
        name: str | None = None,
    ) -> int:
        """Add an acquired view; the map is never reset.

        Args:
            camera: the view's camera (OpenCV axes).
            image: RGB [H, W, 3] in [0, 1] (float; clamped, values beyond [-0.5, 1.5] are
                refused) or uint8, H and W the camera's.
            depth: optional depth along the optical axis [H, W] (≤ 0 or NaN: unknown).
            name: optional label (default ``view_<index>``).

        Returns:
            The view's index in :attr:`views`.
        """
        if not isinstance(camera, Camera):
            raise TypeError(f"camera must be a Camera, got {type(camera).__name__}")
        h, w = camera.height, camera.width
        if not isinstance(image, Tensor):
            raise TypeError(f"image must be a torch.Tensor, got {type(image).__name__}")
        if image.shape != (h, w, 3):
            raise ValueError(
                f"image must have shape [{h}, {w}, 3] (the camera's size), got {list(image.shape)}"
            )
        if image.dtype == torch.uint8:
            img = image.to(self.dtype) / 255.0
        else:
            img = image.detach().to(self.dtype)
            if not torch.isfinite(img).all():
                raise ValueError("image contains NaN or infinite values")
            lo, hi = float(img.min()), float(img.max())
            if lo < -0.5 or hi > 1.5:  # e.g. 0-255 data in a float tensor
                raise ValueError(
                    f"image values must be in [0, 1] (uint8 is also accepted), "
                    f"got [{lo:.4g}, {hi:.4g}]"
                )
            img = img.clamp(0, 1)  # renders may overshoot slightly (SH colours are not capped)
        dep = None
        if depth is not None:
            if not isinstance(depth, Tensor):
                raise TypeError(f"depth must be a torch.Tensor, got {type(depth).__name__}")
            if depth.shape != (h, w):
                raise ValueError(f"depth must have shape [{h}, {w}], got {list(depth.shape)}")
            dep = depth.detach().to(self.dtype)
            dep = torch.where(torch.isfinite(dep) & (dep > 0), dep, torch.zeros_like(dep))
        cam = Camera(
            c2w=camera.c2w.detach().to(self.device, self.dtype), intrinsics=camera.intrinsics
        )
        with self._lock:
            idx = len(self._views)
            view = View(
                name=name if name is not None else f"view_{idx}",
                camera=cam,
                image=img.to(self.device).contiguous(),
                depth=None if dep is None else dep.to(self.device).contiguous(),
            )
            self._views.append(view)
            if view.depth is not None and self.config.extend_from_depth:
                self._extend_from_view(view)
        return idx

    # ------------------------------------------------------------------ initialisation
    def init_from_points(
        self,
        points: Tensor,
        colors: Tensor | None = None,
        *,
        opacity: float | None = None,
        append: bool = False,
    ) -> int:
        """Create Gaussians at ``points`` [P, 3] with ``colors`` [P, 3] in [0, 1].

        Scales are isotropic, from the nearest-neighbour distances
        (:func:`nearest_neighbour_scales`), opacity ``opacity`` (default
        ``config.init_opacity``), identity rotations, SH DC from the colour.

        Args:
            append: add to the current Gaussians (their state is untouched) instead of
                replacing them (the default: a fresh map, reported with ``reason="init"``).

        Returns:
            Number of Gaussians created.
        """
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"points must have shape [P, 3], got {list(points.shape)}")
        if colors is None:
            colors = torch.full_like(points, 0.5)
        if colors.shape != points.shape:
            raise ValueError(
                f"colors must have the shape of points {list(points.shape)}, got "
                f"{list(colors.shape)}"
            )
        pts = points.detach().to(self.device, self.dtype)
        cols = colors.detach().to(self.device, self.dtype)
        keep = torch.isfinite(pts).all(dim=1) & torch.isfinite(cols).all(dim=1)
        if not bool(keep.all()):
            log.warning("init_from_points: dropping %d non-finite points", int((~keep).sum()))
            pts, cols = pts[keep], cols[keep]
        with self._lock:
            return self._add_points(pts, cols.clamp(0, 1), opacity, append=append)

    def init_from_depth(
        self,
        views: Sequence[Any] | None = None,
        *,
        stride: int | None = None,
        max_points: int | None = None,
        opacity: float | None = None,
        append: bool = False,
    ) -> int:
        """Back-project RGB-D views (subsampled) into initial Gaussians.

        Args:
            views: objects with ``camera``, ``image`` [H, W, 3] and ``depth`` [H, W] attributes
                (e.g. :class:`~agilegs.service.data.loaders.View`); None: the acquired views
                that have depth. Views without depth are skipped. The views are not added to
                the training set (use :meth:`add_view`).
            stride: pixel stride (default ``config.init_stride``).
            max_points: random subsample to at most this many points in all (default
                ``config.init_max_points``), with the seeded generator.
            opacity: initial opacity (default ``config.init_opacity``).
            append: add to the current map instead of replacing it.

        Returns:
            Number of Gaussians created.
        """
        stride = self.config.init_stride if stride is None else int(stride)
        if stride < 1:
            raise ValueError(f"stride must be >= 1, got {stride}")
        max_points = self.config.init_max_points if max_points is None else int(max_points)
        with self._lock:
            src_views = list(self._views) if views is None else list(views)
            pts_l, col_l = [], []
            for i, v in enumerate(src_views):
                d = getattr(v, "depth", None)
                cam = getattr(v, "camera", None)
                if d is None:
                    continue
                if not isinstance(cam, Camera):
                    raise TypeError(f"views[{i}].camera must be a Camera")
                img = getattr(v, "image", None)
                cam_d = Camera(
                    c2w=cam.c2w.detach().to(self.device, self.dtype), intrinsics=cam.intrinsics
                )
                p, c = backproject_depth(
                    cam_d,
                    d.detach().to(self.device, self.dtype),
                    None if img is None else img.detach().to(self.device, self.dtype),
                    stride=stride,
                )
                pts_l.append(p)
                col_l.append(c)
            if not pts_l:
                raise ValueError("init_from_depth: no view with a depth map")
            pts = torch.cat(pts_l)
            cols = torch.cat(col_l)
            pts, cols = self._subsample(pts, cols, max_points)
            if pts.shape[0] == 0:
                raise ValueError("init_from_depth: the depth maps have no valid pixel")
            return self._add_points(pts, cols.clamp(0, 1), opacity, append=append)

    def replace_gmap(self, gmap: GaussianMap, src: Tensor | None = None) -> None:
        """Replace the Gaussians (e.g. a trainer pushing its map). The views are kept.

        Args:
            gmap: the new map (copied to the mapper's device and dtype).
            src: optional LongTensor [N_new] relating the new Gaussians to the current ones
                (as in :class:`TopologyChange`); Adam moments are carried where ``src >= 0``.
                None: all new (``src = -1``).
        """
        if not isinstance(gmap, GaussianMap):
            raise TypeError(f"gmap must be a GaussianMap, got {type(gmap).__name__}")
        n_new = gmap.num_gaussians
        with self._lock:
            n_old = self.num_gaussians
            if src is None:
                s = torch.full((n_new,), -1, dtype=torch.long, device=self.device)
            else:
                if src.shape != (n_new,):
                    raise ValueError(f"src must have shape [{n_new}], got {list(src.shape)}")
                s = src.to(self.device).long()
                if s.numel() and (int(s.max()) >= n_old or int(s.min()) < -1):
                    raise ValueError(f"src must be in [-1, {n_old - 1}]")
            self._sh_degree = gmap.sh_degree
            new = self._split_sh(gmap.detach().to(self.device, self.dtype))
            identity = s >= 0
            self._apply_change(new, s, identity, reason="replace", counts={"added": n_new})

    # ------------------------------------------------------------------ training
    def step(self, n: int = 1) -> dict[str, Any]:
        """Run ``n`` training steps.

        Returns:
            {"loss": last step's loss, "loss_mean": mean over the n steps, "l1", "dssim",
            "depth_l1" (last step; None without depth), "view": last view index,
            "num_gaussians", "num_steps", "num_views", "cloned", "split", "pruned",
            "opacity_resets" (totals over the n steps)}.
        """
        if int(n) < 1:
            raise ValueError(f"n must be >= 1, got {n}")
        with self._lock:
            if not self._views:
                raise RuntimeError("no views to train on: call add_view first")
            if self.num_gaussians == 0:
                raise RuntimeError(
                    "the map has no Gaussians: pass a gmap, call init_from_depth / "
                    "init_from_points, or add a view with depth"
                )
            if self._extent is None:
                self._extent = self._estimate_extent()
                log.info("scene extent estimated as %.4g", self._extent)
                self._update_lr()
            totals = {"cloned": 0, "split": 0, "pruned": 0, "opacity_resets": 0}
            losses: list[float] = []
            info: dict[str, Any] = {}
            for _ in range(int(n)):
                info = self._train_step()
                losses.append(info["loss"])
                for k in ("cloned", "split", "pruned", "opacity_resets"):
                    totals[k] += int(info.get(k, 0))
            return {
                "loss": losses[-1],
                "loss_mean": sum(losses) / len(losses),
                "l1": info["l1"],
                "dssim": info["dssim"],
                "depth_l1": info["depth_l1"],
                "view": info["view"],
                "num_gaussians": self.num_gaussians,
                "num_steps": self._num_steps,
                "num_views": len(self._views),
                **totals,
            }

    def loss_on_view(self, view: int | View) -> dict[str, float]:
        """Training loss terms of one view (acquired index or a View) without a step."""
        with self._lock, torch.no_grad():
            v = self._views[view] if isinstance(view, int) else view
            if v.image is None:
                raise ValueError("view has no image")
            out = render(
                self._render_map(), v.camera, background=self._bg, tile_size=self.config.tile_size
            )
            img = v.image.to(self.device, self.dtype)
            l1 = (out.rgb - img).abs().mean()
            ds = ssim_loss(out.rgb, img)
            lam = self.config.lambda_dssim
            return {"loss": float((1 - lam) * l1 + lam * ds), "l1": float(l1), "dssim": float(ds)}

    # ------------------------------------------------------------------ internals
    def _empty_map(self) -> GaussianMap:
        k = (self._sh_degree + 1) ** 2
        z = torch.zeros
        return GaussianMap(
            means=z(0, 3, dtype=self.dtype, device=self.device),
            log_scales=z(0, 3, dtype=self.dtype, device=self.device),
            quats=z(0, 4, dtype=self.dtype, device=self.device),
            opacity_logits=z(0, dtype=self.dtype, device=self.device),
            sh=z(0, k, 3, dtype=self.dtype, device=self.device),
        )

    @staticmethod
    def _split_sh(g: GaussianMap) -> dict[str, Tensor]:
        return {
            "means": g.means,
            "log_scales": g.log_scales,
            "quats": g.quats,
            "opacity_logits": g.opacity_logits,
            "sh_dc": g.sh[:, :1],
            "sh_rest": g.sh[:, 1:],
        }

    def _render_map(self) -> GaussianMap:
        p = self._params
        k = (self.active_sh_degree + 1) ** 2
        sh = torch.cat([p["sh_dc"], p["sh_rest"][:, : k - 1]], dim=1)
        return GaussianMap(
            means=p["means"],
            log_scales=p["log_scales"],
            quats=p["quats"],
            opacity_logits=p["opacity_logits"],
            sh=sh,
        )

    def _lr(self, key: str) -> float:
        c = self.config
        ext = self._extent if self._extent is not None else 1.0
        if key == "means":
            t = min(1.0, self._num_steps / c.lr_means_steps)
            return ext * math.exp((1 - t) * math.log(c.lr_means) + t * math.log(c.lr_means_final))
        return {
            "log_scales": c.lr_log_scales,
            "quats": c.lr_quats,
            "opacity_logits": c.lr_opacity,
            "sh_dc": c.lr_sh_dc,
            "sh_rest": c.lr_sh_rest,
        }[key]

    def _update_lr(self) -> None:
        if self._opt is None:
            return
        for g in self._opt.param_groups:
            g["lr"] = self._lr(g["name"])

    def _install(self, new: dict[str, Tensor], carry: tuple[Tensor, Tensor] | None) -> None:
        """Make ``new`` the live leaf tensors and rebuild Adam.

        ``carry = (src, identity)``: moments of new row j copied from old row src[j] where
        identity[j]; zero elsewhere. None: all moments zero.
        """
        old_params = self._params
        old_state = self._opt.state if self._opt is not None else {}
        params = {
            k: new[k].detach().to(self.device, self.dtype).contiguous().clone().requires_grad_(True)
            for k in _PARAM_KEYS
        }
        groups = [
            {"params": [params[k]], "lr": self._lr(k), "name": k}
            for k in _PARAM_KEYS
            if params[k].numel() > 0
        ]
        opt = torch.optim.Adam(groups, lr=1e-3, eps=self.config.adam_eps) if groups else None
        if opt is not None and carry is not None:
            src, identity = carry
            for k in _PARAM_KEYS:
                p_old = old_params.get(k)
                st = old_state.get(p_old) if p_old is not None else None
                if not st or "exp_avg" not in st or params[k].numel() == 0:
                    continue
                rows = identity.nonzero().squeeze(1)
                m = torch.zeros_like(params[k])
                v = torch.zeros_like(params[k])
                m[rows] = st["exp_avg"][src[rows]]
                v[rows] = st["exp_avg_sq"][src[rows]]
                step = st["step"].clone() if isinstance(st["step"], Tensor) else st["step"]
                opt.state[params[k]] = {"step": step, "exp_avg": m, "exp_avg_sq": v}
        self._params = params
        self._opt = opt

    def _reset_stats(self) -> None:
        n = self.num_gaussians
        self._grad_accum = torch.zeros(n, dtype=self.dtype, device=self.device)
        self._grad_count = torch.zeros(n, dtype=torch.int64, device=self.device)
        self._max_radii = torch.zeros(n, dtype=self.dtype, device=self.device)

    def _apply_change(
        self,
        new: dict[str, Tensor],
        src: Tensor,
        identity: Tensor,
        *,
        reason: str,
        counts: dict[str, int],
        reset_stats: bool = False,
    ) -> None:
        n_old = self.num_gaussians
        n_new = int(src.shape[0])
        kept = torch.zeros(n_old, dtype=torch.bool, device=self.device)
        if n_old:
            kept[src[identity]] = True
        self._install(new, carry=(src, identity))
        if reset_stats:
            self._reset_stats()
        else:
            stats = remap_per_gaussian(
                {"a": self._grad_accum, "c": self._grad_count, "r": self._max_radii},
                torch.where(identity, src, torch.full_like(src, -1)),
                0,
            )
            self._grad_accum, self._grad_count, self._max_radii = stats["a"], stats["c"], stats["r"]
        change = TopologyChange(
            src=src.clone(),
            kept=kept,
            identity=identity.clone(),
            num_old=n_old,
            num_new=n_new,
            reason=reason,
            counts=dict(counts),
        )
        log.debug("topology change %s: %d -> %d %s", reason, n_old, n_new, counts)
        for cb in list(self.on_topology_change):
            cb(change)

    def _subsample(
        self, pts: Tensor, cols: Tensor, max_points: int | None
    ) -> tuple[Tensor, Tensor]:
        if max_points is not None and pts.shape[0] > max_points:
            idx = torch.randperm(pts.shape[0], generator=self._gen_points)[:max_points]
            idx = idx.sort().values.to(pts.device)
            return pts[idx], cols[idx]
        return pts, cols

    def _add_points(self, pts: Tensor, cols: Tensor, opacity: float | None, *, append: bool) -> int:
        op = self.config.init_opacity if opacity is None else float(opacity)
        if not 0.0 < op < 1.0:
            raise ValueError(f"opacity must be in (0, 1), got {op}")
        n_old = self.num_gaussians if append else 0
        cap = self.config.max_gaussians
        if cap is not None and n_old + pts.shape[0] > cap:
            room = max(0, cap - n_old)
            log.warning("max_gaussians=%d: keeping %d of %d new points", cap, room, pts.shape[0])
            pts, cols = self._subsample(pts, cols, room)
        p = int(pts.shape[0])
        if p == 0:
            return 0
        scales = nearest_neighbour_scales(pts)
        g = GaussianMap.from_points(pts, cols, scale=scales, opacity=op, sh_degree=self._sh_degree)
        add = self._split_sh(g)
        dev = self.device
        if append and self.num_gaussians:
            cur = self._params
            new = {k: torch.cat([cur[k].detach(), add[k]]) for k in _PARAM_KEYS}
            src = torch.cat(
                [
                    torch.arange(n_old, device=dev),
                    torch.full((p,), -1, dtype=torch.long, device=dev),
                ]
            )
            identity = src >= 0
            self._apply_change(new, src, identity, reason="extend", counts={"added": p})
        else:
            src = torch.full((p,), -1, dtype=torch.long, device=dev)
            self._apply_change(
                add, src, src >= 0, reason="init", counts={"added": p}, reset_stats=True
            )
        return p

    def _extend_from_view(self, view: View) -> int:
        assert view.depth is not None and view.image is not None
        c = self.config
        if self.num_gaussians == 0:
            pts, cols = backproject_depth(view.camera, view.depth, view.image, stride=c.init_stride)
            pts, cols = self._subsample(pts, cols, c.init_max_points)
            return self._add_points(pts, cols, None, append=False) if pts.shape[0] else 0
        with torch.no_grad():
            out = render(self._render_map(), view.camera, tile_size=c.tile_size)
        mask = out.alpha < c.extend_alpha_threshold
        pts, cols = backproject_depth(
            view.camera, view.depth, view.image, stride=c.init_stride, mask=mask
        )
        pts, cols = self._subsample(pts, cols, c.init_max_points)
        if pts.shape[0] == 0:
            return 0
        return self._add_points(pts, cols, None, append=True)

    def _estimate_extent(self) -> float:
        if len(self._views) >= 2:
            centres = torch.stack([v.camera.position for v in self._views]).double()
            r = float((centres - centres.mean(0)).norm(dim=1).max())
            if r > 1e-6:
                return 1.1 * r
        means = self._params["means"].detach().double()
        if means.shape[0] >= 2:
            q = torch.quantile(
                means, torch.tensor([0.02, 0.98], dtype=means.dtype, device=means.device), dim=0
            )
            r = 0.5 * float((q[1] - q[0]).norm())
            if r > 1e-6:
                return 1.1 * r
        return 1.0

    def _train_step(self) -> dict[str, Any]:
        c = self.config
        assert self._opt is not None
        i = int(torch.randint(len(self._views), (1,), generator=self._gen_views))
        view = self._views[i]
        assert view.image is not None
        out = render(self._render_map(), view.camera, background=self._bg, tile_size=c.tile_size)
        l1 = (out.rgb - view.image).abs().mean()
        ds = ssim_loss(out.rgb, view.image)
        loss = (1.0 - c.lambda_dssim) * l1 + c.lambda_dssim * ds
        depth_l1: Tensor | None = None
        if view.depth is not None and c.lambda_depth > 0:
            valid = view.depth > 0
            if bool(valid.any()):
                depth_l1 = (out.depth - view.depth)[valid].abs().mean()
                loss = loss + c.lambda_depth * depth_l1
        means2d = out.means2d
        if means2d.requires_grad:
            means2d.retain_grad()
        if loss.requires_grad:
            self._opt.zero_grad(set_to_none=True)
            loss.backward()
            with torch.no_grad():
                vis = out.radii > 0
                g = means2d.grad
                if g is not None:
                    scale = torch.tensor(
                        [0.5 * view.camera.width, 0.5 * view.camera.height],
                        dtype=g.dtype,
                        device=g.device,
                    )
                    gn = (g * scale).norm(dim=-1).to(self.dtype)
                    self._grad_accum[vis] += gn[vis]
                    self._grad_count[vis] += 1
                self._max_radii[vis] = torch.maximum(
                    self._max_radii[vis], out.radii[vis].to(self.dtype)
                )
            self._opt.step()
        self._num_steps += 1
        self._last_loss = float(loss.detach())
        info: dict[str, Any] = {
            "loss": self._last_loss,
            "l1": float(l1.detach()),
            "dssim": float(ds.detach()),
            "depth_l1": None if depth_l1 is None else float(depth_l1.detach()),
            "view": i,
        }
        self._update_lr()
        s = self._num_steps
        in_window = c.densify_until is None or s <= c.densify_until
        if c.densify and in_window and s >= c.densify_from and s % c.densify_every == 0:
            info.update(self._densify_and_prune())
        if c.opacity_reset_every is not None and in_window and s % c.opacity_reset_every == 0:
            self._reset_opacity()
            info["opacity_resets"] = 1
        return info

    @torch.no_grad()
    def _densify_and_prune(self) -> dict[str, int]:
        c = self.config
        assert self._extent is not None
        ext = self._extent
        p = {k: v.detach() for k, v in self._params.items()}
        n = self.num_gaussians
        dev = self.device
        grads = torch.where(
            self._grad_count > 0,
            self._grad_accum / self._grad_count.clamp_min(1).to(self.dtype),
            torch.zeros_like(self._grad_accum),
        )
        max_scale = p["log_scales"].exp().amax(dim=1)
        cand = grads >= c.densify_grad_threshold
        small = max_scale <= c.percent_dense * ext
        # cap: keep the candidates with the largest gradients that fit
        if c.max_gaussians is not None and bool(cand.any()):
            idx = cand.nonzero().squeeze(1)
            order = idx[grads[idx].argsort(descending=True)]
            cost = torch.where(small[order], 1, c.split_samples - 1)
            fits = cost.cumsum(0) <= max(0, c.max_gaussians - n)
            cand = torch.zeros_like(cand)
            cand[order[fits]] = True
        clone = cand & small
        split = cand & ~small
        n_clone, n_split = int(clone.sum()), int(split.sum())

        # kept old (not split), clones, split children: in that order
        keep_idx = (~split).nonzero().squeeze(1)
        clone_idx = clone.nonzero().squeeze(1)
        split_idx = split.nonzero().squeeze(1)
        k = c.split_samples
        child_src = split_idx.repeat(k)
        parts: dict[str, list[Tensor]] = {key: [p[key][keep_idx], p[key][clone_idx]] for key in p}
        if n_split:
            stds = p["log_scales"][child_src].exp()
            z = torch.randn(stds.shape, generator=self._gen_split, device=dev, dtype=self.dtype)
            rot = quat_to_rotmat(p["quats"][child_src])
            new_means = (rot @ (z * stds)[..., None])[..., 0] + p["means"][child_src]
            new_ls = p["log_scales"][child_src] - math.log(c.split_scale_divisor)
        for key in p:
            if key == "means" and n_split:
                parts[key].append(new_means)
            elif key == "log_scales" and n_split:
                parts[key].append(new_ls)
            else:
                parts[key].append(p[key][child_src])
        dens = {key: torch.cat(v) for key, v in parts.items()}
        src = torch.cat([keep_idx, clone_idx, child_src])
        identity = torch.cat(
            [
                torch.ones(keep_idx.numel(), dtype=torch.bool, device=dev),
                torch.zeros(clone_idx.numel() + child_src.numel(), dtype=torch.bool, device=dev),
            ]
        )
        # prune (on the densified set; new Gaussians have no screen-radius history)
        opac = torch.sigmoid(dens["opacity_logits"])
        prune = opac < c.prune_opacity
        if c.prune_large_from is not None and self._num_steps > c.prune_large_from:
            radii = torch.zeros(src.numel(), dtype=self.dtype, device=dev)
            radii[: keep_idx.numel()] = self._max_radii[keep_idx]
            big_ws = dens["log_scales"].exp().amax(dim=1) > c.max_world_scale * ext
            prune = prune | (radii > c.max_screen_radius) | big_ws
        if bool(prune.all()) and prune.numel():
            log.warning("pruning would remove every Gaussian; keeping the most opaque one")
            prune[opac.argmax()] = False
        n_pruned = int(prune.sum())
        if n_clone == 0 and n_split == 0 and n_pruned == 0:
            self._reset_stats()
            return {"cloned": 0, "split": 0, "pruned": 0}
        keep = ~prune
        new = {key: v[keep] for key, v in dens.items()}
        counts = {"cloned": n_clone, "split": n_split, "pruned": n_pruned}
        self._apply_change(
            new, src[keep], identity[keep], reason="densify", counts=counts, reset_stats=True
        )
        return counts

    @torch.no_grad()
    def _reset_opacity(self) -> None:
        p = self._params["opacity_logits"]
        cap = math.log(self.config.opacity_reset_value / (1 - self.config.opacity_reset_value))
        p.clamp_(max=cap)
        if self._opt is not None and p in self._opt.state:
            st = self._opt.state[p]
            st["exp_avg"].zero_()
            st["exp_avg_sq"].zero_()
