"""``agilegs bench render --device cuda``: the rasterizers, the Fisher and a training step on a GPU.

For each Gaussian count and image size, on the same map and camera, rounds of (the median of
``--repeats``, each timed between two device synchronisations, after a warm-up round):

- ``fwd``, ``fwd+bwd``: this project's rasterizer (:func:`render`, forward alone, forward and
  backward of a weighted sum of the image), in pure torch on the GPU;
- ``fisher``: its exact diagonal Fisher (:func:`fisher_diag`, all five blocks) as it runs by
  default (the moments by the Triton kernel where Triton loads), ``moments`` those moments
  alone (:func:`screen_second_moments`), and ``fisher torch`` the pure-torch reference
  (``backend="torch"``; at most two timed rounds: it is slow), with ``fisher_agree`` the
  largest difference between the two, relative to each block's largest entry;
- ``gsplat fwd``, ``gsplat fwd+bwd``: gsplat's ``rasterization`` (when it loads);
- ``gsplat step``: gsplat's forward and backward of the L1 loss against a target image, plus an
  Adam step over the map's fields (the yardstick of a training step);
- ``mapper step``: one :meth:`Mapper.step` on that map and camera with its training loss (L1 +
  D-SSIM), densification statistics and learning-rate schedule, through
  ``MapperConfig.rasterizer`` ``auto`` (gsplat where it loads);
- ``agree``: the largest and mean |rgb| difference between the two rasterizers' images;
- ``anchor pool``, ``anchor grad`` and their ``torch`` references: the anchor's proxy ψ at a
  pool of 100 poses and its gradient at 4 starts (:mod:`agilegs.lab.bench.anchor_gpu`; on
  CUDA by its Triton kernels), with ``anchor_agree``.

Each timed kind also reports its peak GPU memory above the map's (``torch.cuda``'s allocator
statistics), i.e. what a session pays per render at that size.
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
import sys
import time
from collections.abc import Callable
from typing import Any

logger = logging.getLogger(__name__)

GPU_KINDS = ("fwd", "fwd_bwd", "fisher", "moments", "fisher_torch", "gsplat_fwd",
             "gsplat_fwd_bwd", "gsplat_step", "mapper_step", "anchor_pool", "anchor_grad",
             "anchor_pool_torch", "anchor_grad_torch")
SLOW_ROUNDS = {"fisher_torch": 2}
"""Kinds timed over fewer rounds than ``--repeats``."""


def parse_size(text: str) -> tuple[int, int]:
    """``"512"`` -> (512, 512); ``"1024x768"`` -> (1024, 768) (width x height)."""
    w, _, h = text.lower().partition("x")
    width, height = int(w), int(h or w)
    if width < 1 or height < 1:
        raise ValueError(f"image size must be positive, got {text!r}")
    return width, height


def _build(scene: str | None, n: int, width: int, height: int, device: Any) -> tuple[Any, Any]:
    import torch

    from agilegs.lab.bench.latency import densified
    from agilegs.lab.bench.scenes import random_cube
    from agilegs.service.nbv import Camera, load_scene, look_at

    if scene:
        gm = densified(load_scene(scene), n, seed=0)
        c = gm.means.median(dim=0).values
        spread = (gm.means - c).norm(dim=1).quantile(0.9)
        eye = c + spread * torch.tensor([0.0, -0.6, -1.6])
        c2w = look_at(eye, c)
    else:
        gm, c2w = random_cube(n, sh_coeffs=16)
    f = 0.9 * width
    cam = Camera.from_c2w(c2w, fx=f, fy=f, cx=width / 2, cy=height / 2, width=width,
                          height=height)
    return gm.to(device=device, dtype=torch.float32), cam.to(device=device)


def _functions(gm: Any, cam: Any, with_gsplat: bool
               ) -> tuple[dict[str, Callable[[], Any]], str]:
    """The timed kinds, and the rasterizer the mapper's step trains with."""
    import torch

    from agilegs.config.mapper import MapperConfig
    from agilegs.service.mapper.gsplat_render import render_gsplat
    from agilegs.service.mapper.mapper import Mapper
    from agilegs.service.nbv import fisher_diag, render
    from agilegs.service.nbv.information import screen_second_moments

    gen = torch.Generator(device=gm.means.device).manual_seed(1)
    weight = torch.rand(cam.height, cam.width, 3, generator=gen, device=gm.means.device)
    with torch.no_grad():
        target = render(gm, cam).rgb.detach().clamp(0, 1) * 0.9

    def fwd_bwd(fn: Callable[..., Any]) -> Callable[[], None]:
        def run() -> None:
            g = gm.clone().requires_grad_()
            (fn(g, cam).rgb * weight).sum().backward()
        return run

    fns: dict[str, Callable[[], Any]] = {
        "fwd": lambda: render(gm, cam),
        "fwd_bwd": fwd_bwd(render),
        "fisher": lambda: fisher_diag(gm, cam),
        "moments": lambda: screen_second_moments(gm, cam),
        "fisher_torch": lambda: fisher_diag(gm, cam, backend="torch"),
    }
    if with_gsplat:
        params = [t.detach().clone().requires_grad_() for t in gm.tensors().values()]
        opt = torch.optim.Adam(params, lr=1e-4, eps=1e-15)
        names = list(gm.tensors().keys())

        def gsplat_step() -> None:
            from agilegs.service.nbv import GaussianMap

            g = GaussianMap(**dict(zip(names, params, strict=True)))
            loss = (render_gsplat(g, cam).rgb - target).abs().mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()

        fns["gsplat_fwd"] = lambda: render_gsplat(gm, cam)
        fns["gsplat_fwd_bwd"] = fwd_bwd(render_gsplat)
        fns["gsplat_step"] = gsplat_step
    cfg = MapperConfig(densify_from=10**9, opacity_reset_every=None, scene_extent=1.0,
                       sh_degree_interval=None, extend_from_depth=False, max_gaussians=None)
    mapper = Mapper(gm, cfg, device=gm.means.device)
    mapper.add_view(cam, target)
    fns["mapper_step"] = lambda: mapper.step(1)
    return fns, mapper.rasterizer


def _time_gpu(scene: str | None, n: int, width: int, height: int, repeats: int,
              device: str, *, anchor_samples: int | None = None, anchor_pool: int = 100
              ) -> dict[str, Any]:
    """One row: every kind timed on ``device`` (a CUDA device; ``"cpu"`` runs the same code
    without gsplat and memory figures, for tests). ``anchor_samples``, ``anchor_pool``: the
    anchor's proxy sample (default: the anchor's) and pool."""
    import torch

    from agilegs.service.mapper.gsplat_render import gsplat_status, render_gsplat
    from agilegs.service.nbv import render
    from agilegs.service.nbv.kernels.gpu import gpu_moments_apply

    from .anchor_gpu import anchor_functions

    dev = torch.device(device)
    cuda = dev.type == "cuda"

    def sync() -> None:
        if cuda:
            torch.cuda.synchronize(dev)

    def allocated(peak: bool = False) -> int:
        if not cuda:
            return 0
        return torch.cuda.max_memory_allocated(dev) if peak else torch.cuda.memory_allocated(dev)

    why = gsplat_status() if cuda else "not a CUDA device"
    gm, cam = _build(scene, n, width, height, dev)
    sync()
    base_mem = allocated()
    fns, mapper_rasterizer = _functions(gm, cam, why is None)
    anchor_fns, anchor = anchor_functions(gm, cam, samples=anchor_samples, pool=anchor_pool)
    fns.update(anchor_fns)
    kinds = [k for k in GPU_KINDS if k in fns]
    wall: dict[str, list[float]] = {k: [] for k in kinds}
    peak: dict[str, float] = {}
    fishers: dict[str, dict[str, Any]] = {}  # the warm-up's two Fishers, in host memory
    for k in kinds:  # warm-up, and each kind's peak memory above the map's
        sync()
        if cuda:
            torch.cuda.reset_peak_memory_stats(dev)
        out = fns[k]()
        sync()
        peak[k] = (allocated(peak=True) - base_mem) / 2**20
        if k in ("fisher", "fisher_torch"):
            fishers[k] = {f: v.detach().cpu() for f, v in out.items()}
        del out
    for rnd in range(repeats):
        for k in kinds:
            if rnd >= SLOW_ROUNDS.get(k, repeats):
                continue
            sync()
            t0 = time.perf_counter()
            fns[k]()
            sync()
            wall[k].append((time.perf_counter() - t0) * 1e3)
    row: dict[str, Any] = {
        "gaussians": n, "width": width, "height": height,
        "ms": {k: statistics.median(v) for k, v in wall.items()},
        "peak_mb": peak, "map_mb": base_mem / 2**20,
        "gsplat": why is None, "gsplat_unavailable": why,
        "mapper_rasterizer": mapper_rasterizer,
        "fisher_path": "triton" if gpu_moments_apply(None, gm.means) else "torch",
        "anchor_samples": anchor["samples"], "anchor_slots": anchor["slots"],
        "anchor_pool": anchor["pool"],
    }
    row["anchor_agree"], row["anchor_path"] = anchor["agree"]()
    fast, ref = fishers["fisher"], fishers["fisher_torch"]
    row["fisher_agree"] = max(
        float((fast[f] - ref[f]).abs().max() / ref[f].abs().max().clamp_min(1e-30)) for f in ref)
    if why is None:
        with torch.no_grad():
            a, b = render(gm, cam), render_gsplat(gm, cam)
        d = (a.rgb - b.rgb).abs()
        row["agree"] = {"rgb_max_abs": float(d.max()), "rgb_mean_abs": float(d.mean()),
                        "alpha_mean_abs": float((a.alpha - b.alpha).abs().mean())}
        row["mapper_over_gsplat_step"] = row["ms"]["mapper_step"] / row["ms"]["gsplat_step"]
    return row


def run_gpu(args: argparse.Namespace) -> int:
    import torch

    if not torch.cuda.is_available():
        raise SystemExit(f"--device {args.device}: CUDA is not available here")
    try:
        sizes = [parse_size(s) for s in str(args.sizes).split(",") if s]
    except ValueError as exc:
        raise SystemExit(f"--sizes: {exc}") from None
    counts = [int(s) for s in str(args.gaussians).split(",") if s]
    if not sizes or not counts or min(counts) < 1 or args.repeats < 1:
        raise SystemExit("--sizes and --gaussians need positive values, --repeats >= 1")
    rows = []
    for n in counts:
        for w, h in sizes:
            row = _time_gpu(args.scene, n, w, h, args.repeats, args.device)
            rows.append(row)
            logger.info("%d Gaussians at %dx%d: %s", n, w, h, row["ms"])
            torch.cuda.empty_cache()
    _print(rows, args)
    result = {
        "config": {"scene": args.scene, "repeats": args.repeats, "torch": torch.__version__,
                   "device": torch.cuda.get_device_name(torch.device(args.device))},
        "rows": rows,
    }
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(result, fh, indent=2)
    return 0


def _print(rows: list[dict[str, Any]], args: argparse.Namespace) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"agilegs bench render on {args.device}: median ms of {args.repeats} "
                  "rounds (peak GPU MB above the map)")
    cols = ["N", "px", "fwd", "fwd+bwd", "fisher", "moments", "fisher torch", "agree",
            "gsplat fwd", "gsplat f+b", "gsplat step", "mapper step", "mapper / gsplat step",
            "gsplat agree max|mean", "ψ pool", "ψ grad", "ψ torch pool|grad", "ψ agree"]
    for c in cols:
        table.add_column(c, justify="right")
    for r in rows:
        ms, pk = r["ms"], r["peak_mb"]

        def cell(k: str, ms: dict[str, float] = ms, pk: dict[str, float] = pk) -> str:
            return "-" if k not in ms else f"{ms[k]:.1f} ({pk[k]:.0f})"

        agree = r.get("agree")
        table.add_row(
            str(r["gaussians"]), f"{r['width']}x{r['height']}", cell("fwd"), cell("fwd_bwd"),
            cell("fisher") + ("" if r["fisher_path"] == "torch" else " " + r["fisher_path"]),
            cell("moments"), cell("fisher_torch"), f"{r['fisher_agree']:.1e}",
            cell("gsplat_fwd"), cell("gsplat_fwd_bwd"), cell("gsplat_step"),
            cell("mapper_step") + ("" if r["mapper_rasterizer"] == "gsplat" else " builtin"),
            f"{r['mapper_over_gsplat_step']:.2f}×" if "mapper_over_gsplat_step" in r else "-",
            "-" if agree is None else f"{agree['rgb_max_abs']:.3f}|{agree['rgb_mean_abs']:.1e}",
            cell("anchor_pool") + f" {r['anchor_path']}", cell("anchor_grad"),
            f"{ms['anchor_pool_torch']:.1f}|{ms['anchor_grad_torch']:.1f}",
            f"{r['anchor_agree']:.1e}")
    console = Console(file=sys.stdout, width=240)
    console.print(table)
    missing = next((r["gsplat_unavailable"] for r in rows if not r["gsplat"]), None)
    if missing:
        console.print(f"gsplat not timed: {missing}")
