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

import copy
import logging
import math
import threading
from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor

from agilegs.config.mapper import MapperConfig
from agilegs.service.data.images import View
from agilegs.service.mapper.quality import ssim_loss
from agilegs.service.nbv import Camera, GaussianMap, render

from .densify import plan_densification
from .gsplat_render import render_gsplat, resolve_rasterizer
from .points import backproject_depth, nearest_neighbour_scales
from .topology import TopologyChange, remap_per_gaussian

log = logging.getLogger(__name__)

__all__ = ["Mapper"]

_PARAM_KEYS: tuple[str, ...] = (
    "means",
    "log_scales",
    "quats",
    "opacity_logits",
    "sh_dc",
    "sh_rest",
)


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
        self.rasterizer = resolve_rasterizer(self.config.rasterizer, self.device, self.dtype)
        """The rasterizer that trains: ``"builtin"`` or ``"gsplat"`` (``MapperConfig.rasterizer``
        resolved for this device and dtype)."""
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

    def clone(self) -> Mapper:
        """An independent copy of the whole training state: parameters, optimiser moments,
        densification statistics, views, step counter and random generators. Two clones
        given the same calls train identically; given different views they differ only by
        those views (``agilegs bench value`` branches a run this way)."""
        with self._lock:
            memo = {id(self._lock): threading.RLock(), id(self.on_topology_change): []}
            return copy.deepcopy(self, memo)

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
                (e.g. :class:`~agilegs.service.data.images.View`); None: the acquired views
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
            out = self._render(v.camera, background=self._bg)
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

    def _render(self, camera: Camera, *, background: Tensor | None = None) -> Any:
        """Render the live map through the mapper's rasterizer (a ``RenderResult``)."""
        if self.rasterizer == "gsplat":
            return render_gsplat(self._render_map(), camera, background=background)
        return render(self._render_map(), camera, background=background,
                      tile_size=self.config.tile_size)

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
            out = self._render(view.camera)
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
        out = self._render(view.camera, background=self._bg)
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
                    gn = (g.reshape(-1, 2) * scale).norm(dim=-1).to(self.dtype)
                    self._grad_accum += torch.where(vis, gn, torch.zeros_like(gn))
                    self._grad_count += vis
                # masked updates without boolean indexing: no host synchronisation on a GPU
                self._max_radii = torch.maximum(
                    self._max_radii, torch.where(vis, out.radii.to(self.dtype), 0.0)
                )
            self._opt.step()
        self._num_steps += 1
        losses = torch.stack([loss.detach(), l1.detach(), ds.detach()]).tolist()  # one sync
        self._last_loss = float(losses[0])
        info: dict[str, Any] = {
            "loss": self._last_loss,
            "l1": float(losses[1]),
            "dssim": float(losses[2]),
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
        assert self._extent is not None
        plan = plan_densification(
            {k: v.detach() for k, v in self._params.items()}, self._grad_accum,
            self._grad_count, self._max_radii, self.config, extent=self._extent,
            step=self._num_steps, generator=self._gen_split,
        )
        if plan is None:
            self._reset_stats()
            return {"cloned": 0, "split": 0, "pruned": 0}
        self._apply_change(plan.params, plan.src, plan.identity, reason="densify",
                           counts=plan.counts, reset_stats=True)
        return plan.counts

    @torch.no_grad()
    def _reset_opacity(self) -> None:
        p = self._params["opacity_logits"]
        cap = math.log(self.config.opacity_reset_value / (1 - self.config.opacity_reset_value))
        p.clamp_(max=cap)
        if self._opt is not None and p in self._opt.state:
            st = self._opt.state[p]
            st["exp_avg"].zero_()
            st["exp_avg_sq"].zero_()
