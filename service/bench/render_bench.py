"""``agilegs bench render``: rasterizer and exact-Fisher timings, beside straightforward baselines.

For each resolution and Gaussian count it times, on the same scene and camera:

- ``fwd``: :func:`render` forward alone (no grad);
- ``fwd+bwd``: forward and backward of a sum of the image (analytic backward);
- ``fisher``: :func:`fisher_diag` (exact one-pass diagonal Fisher, all five blocks);
- ``baseline fwd+bwd``: a straightforward pure-torch tile rasterizer with autograd
  (:func:`agilegs.service.bench.render_reference.baseline_render`: the same projection and
  8x8 binning, every tile's list padded to the longest of its chunk of about 2M pairs, every
  (pixel, slot) pair evaluated densely, autograd for the backward);
- ``baseline fisher``: a straightforward one-pass Fisher on the same tiles that forms every
  pair's derivative vector explicitly (``baseline_fisher_diag``).

Times are the process CPU time (median of ``--repeats``; CPU time is what a shared machine
does not inflate), peak memory per configuration in a fresh child process (peak RSS above the
process's RSS after building the scene). The scene is ``--scene`` subsampled to the Gaussian
count, or random Gaussians in a unit cube.
"""

from __future__ import annotations

import argparse
import json
import logging
import multiprocessing as mp
import resource
import statistics
import sys
import time
from typing import Any

logger = logging.getLogger(__name__)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", default=None, help=".ply/.splat scene (default: random Gaussians)")
    p.add_argument("--sizes", default="64,128,256", help="square resolutions")
    p.add_argument("--gaussians", default="5000,20000", help="Gaussian counts")
    p.add_argument("--repeats", type=int, default=3, help="timed repeats (median reported)")
    p.add_argument("--no-baseline", action="store_true", help="skip the straightforward baseline")
    p.add_argument("--threads", type=int, default=0, help="torch threads (0 = torch default)")
    p.add_argument("--json", default=None, help="write the figures to this JSON file")


def _build(scene: str | None, n: int, res: int) -> tuple[Any, Any]:
    import torch

    from agilegs.service.nbv.camera import Camera, look_at
    from agilegs.service.nbv.gaussians import GaussianMap, load_scene

    if scene:
        gm = load_scene(scene, max_gaussians=n, seed=0)
        c = gm.means.median(dim=0).values
        eye = c + torch.tensor([0.0, -0.6, -1.6])
        c2w = look_at(eye, c)
    else:
        g = torch.Generator().manual_seed(0)
        gm = GaussianMap(
            means=torch.rand(n, 3, generator=g) - 0.5,
            log_scales=torch.log(torch.rand(n, 3, generator=g) * 0.02 + 0.005),
            quats=torch.randn(n, 4, generator=g),
            opacity_logits=torch.randn(n, generator=g),
            sh=torch.randn(n, 1, 3, generator=g) * 0.3,
        )
        c2w = look_at(torch.tensor([0.0, 0.0, -2.0]), torch.zeros(3))
    cam = Camera.from_c2w(c2w, fx=res, fy=res, cx=res / 2, cy=res / 2, width=res, height=res)
    return gm, cam


def _time(fn: Any, repeats: int) -> float:
    fn()  # warm-up
    ts = []
    for _ in range(repeats):
        t0 = time.process_time()
        fn()
        ts.append(time.process_time() - t0)
    return statistics.median(ts) * 1e3


def _measure(kind: str, scene: str | None, n: int, res: int, repeats: int, threads: int) -> dict:
    import torch

    from agilegs.service.bench.render_reference import baseline_fisher_diag, baseline_render
    from agilegs.service.nbv.information import fisher_diag
    from agilegs.service.nbv.rasterize import render

    if threads:
        torch.set_num_threads(threads)
    gm, cam = _build(scene, n, res)
    base_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss

    def fwd() -> None:
        with torch.no_grad():
            render(gm, cam)

    def fwd_bwd() -> None:
        g = gm.clone().requires_grad_()
        render(g, cam).rgb.sum().backward()

    def baseline_fwd_bwd() -> None:
        g = gm.clone().requires_grad_()
        baseline_render(g, cam, max_elements=1 << 21).sum().backward()

    fns = {
        "fwd": fwd,
        "fwd_bwd": fwd_bwd,
        "fisher": lambda: fisher_diag(gm, cam),
        "baseline_fwd_bwd": baseline_fwd_bwd,
        "baseline_fisher": lambda: baseline_fisher_diag(gm, cam),
    }
    ms = _time(fns[kind], repeats)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {"ms": ms, "peak_mb": max(peak - base_rss, 0) / 1024.0}


def _child(q: Any, *args: Any) -> None:
    try:
        q.put(_measure(*args))
    except Exception as exc:  # reported to the parent, which prints it
        q.put({"error": repr(exc)})


def run(args: argparse.Namespace) -> int:
    import torch
    from rich.console import Console
    from rich.table import Table

    sizes = [int(s) for s in str(args.sizes).split(",") if s]
    counts = [int(s) for s in str(args.gaussians).split(",") if s]
    kinds = ["fwd", "fwd_bwd", "fisher"] + ([] if args.no_baseline else
                                            ["baseline_fwd_bwd", "baseline_fisher"])
    ctx = mp.get_context("spawn")
    rows = []
    console = Console(file=sys.stdout, width=120)
    for n in counts:
        for res in sizes:
            row: dict[str, Any] = {"gaussians": n, "size": res}
            for kind in kinds:
                q = ctx.Queue()
                proc = ctx.Process(
                    target=_child, args=(q, kind, args.scene, n, res, args.repeats, args.threads)
                )
                proc.start()
                out = q.get()
                proc.join()
                if "error" in out:
                    logger.error("%s at %d² with %d Gaussians failed: %s", kind, res, n, out)
                    return 1
                row[f"{kind}_ms"] = round(out["ms"], 1)
                row[f"{kind}_peak_mb"] = round(out["peak_mb"], 1)
            if "baseline_fwd_bwd_ms" in row:
                row["ratio_fwd_bwd"] = round(row["fwd_bwd_ms"] / row["baseline_fwd_bwd_ms"], 3)
                row["ratio_fisher"] = round(row["fisher_ms"] / row["baseline_fisher_ms"], 3)
            rows.append(row)
    table = Table(title=f"agilegs bench render: median CPU ms of {args.repeats} runs "
                  "(peak MB); ratios: ours / baseline")
    for c in ["N", "px", "fwd", "fwd+bwd", "fisher", "baseline fwd+bwd", "baseline fisher",
              "f+b ratio", "fisher ratio"]:
        table.add_column(c, justify="right")
    for r in rows:

        def cell(kind: str, r: dict[str, Any] = r) -> str:
            if f"{kind}_ms" not in r:
                return "-"
            return f"{r[f'{kind}_ms']:.0f} ({r[f'{kind}_peak_mb']:.0f})"

        table.add_row(
            str(r["gaussians"]),
            f"{r['size']}²",
            cell("fwd"),
            cell("fwd_bwd"),
            cell("fisher"),
            cell("baseline_fwd_bwd"),
            cell("baseline_fisher"),
            f"{r.get('ratio_fwd_bwd', '-')}",
            f"{r.get('ratio_fisher', '-')}",
        )
    console.print(table)
    result = {
        "config": {
            "scene": args.scene,
            "repeats": args.repeats,
            "torch": torch.__version__,
            "threads": args.threads or torch.get_num_threads(),
            "device": "cpu",
        },
        "rows": rows,
    }
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(result, fh, indent=2)
    return 0
