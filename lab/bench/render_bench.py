"""``agilegs bench render``: the compiled kernels beside a straightforward pure-torch baseline.

For each Gaussian count and resolution, on the same scene and camera, one child process times
in interleaved rounds (the median of ``--repeats``):

- ``fwd``, ``fwd+bwd``, ``fisher``: :func:`render` forward alone, forward and backward of a sum
  of the image, and :func:`fisher_diag` (all five blocks), by the compiled kernels
  (``backend="numba"``), at every ``--threads`` count;
- ``baseline fwd+bwd``, ``baseline fisher``: the straightforward pure-torch tile rasterizer
  with autograd and one-pass Fisher of :mod:`agilegs.lab.bench.render_reference`, at the
  first thread count;
- with ``--reference``: the same two through this project's pure-torch path
  (``backend="torch"``), the kernels' reference and fallback.

Times are process CPU time (what a shared machine inflates least) for the ratios, and wall
time for the speed-up of more threads. The kernels run on ``n`` threads with torch itself on
one (``set_kernel_threads``: torch's OpenMP threads would busy-wait on the cores the kernels
need), the baselines on ``n`` torch threads. ``first call`` is the kernels' first forward and
backward in a fresh process (the compiled code loaded from numba's cache, or compiled when
the cache is cold). With ``--memory``, each computation's peak memory is measured in a fresh
child of its own (peak RSS above the RSS after building the scene). The scene is ``--scene``
subsampled to the Gaussian count, or random Gaussians in a unit cube.
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
from collections.abc import Callable
from typing import Any

logger = logging.getLogger(__name__)

KERNEL_KINDS = ("fwd", "fwd_bwd", "fisher")
BASELINE_KINDS = ("baseline_fwd_bwd", "baseline_fisher")
REFERENCE_KINDS = ("reference_fwd_bwd", "reference_fisher")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", default=None, help=".ply/.splat scene (default: random Gaussians)")
    p.add_argument("--sizes", default="64,128,256",
                   help="square resolutions (on a GPU also WIDTHxHEIGHT, e.g. 1024x768)")
    p.add_argument("--gaussians", default="5000,20000", help="Gaussian counts")
    p.add_argument("--repeats", type=int, default=5, help="timed rounds (median reported)")
    p.add_argument("--threads", default="1,2",
                   help="thread counts for the kernels (the baselines run on the first)")
    p.add_argument("--no-baseline", action="store_true", help="skip the straightforward baseline")
    p.add_argument("--reference", action="store_true",
                   help="also time the project's pure-torch path (backend='torch')")
    p.add_argument("--memory", action="store_true",
                   help="measure each computation's peak memory in a child of its own")
    p.add_argument("--json", default=None, help="write the figures to this JSON file")
    p.add_argument("--device", default="cpu",
                   help="cpu (the compiled kernels against the baselines) or cuda (the "
                        "pure-torch rasterizer and Fisher, gsplat and a training step on the "
                        "GPU; agilegs.lab.bench.render_gpu)")


def _build(scene: str | None, n: int, res: int) -> tuple[Any, Any]:
    import torch

    from agilegs.service.nbv import Camera, load_scene, look_at

    if scene:
        gm = load_scene(scene, max_gaussians=n, seed=0)
        c = gm.means.median(dim=0).values
        eye = c + torch.tensor([0.0, -0.6, -1.6])
        c2w = look_at(eye, c)
    else:
        from .scenes import random_cube

        gm, c2w = random_cube(n)
    cam = Camera.from_c2w(c2w, fx=res, fy=res, cx=res / 2, cy=res / 2, width=res, height=res)
    return gm, cam


def _functions(gm: Any, cam: Any) -> dict[str, Callable[[], Any]]:
    import torch

    from agilegs.lab.bench.render_reference import baseline_fisher_diag, baseline_render
    from agilegs.service.nbv import fisher_diag, render
    from agilegs.service.nbv.kernels.backend import Backend

    def fwd() -> None:
        with torch.no_grad():
            render(gm, cam, backend="numba")

    def fwd_bwd(backend: Backend) -> Callable[[], None]:
        def run() -> None:
            g = gm.clone().requires_grad_()
            render(g, cam, backend=backend).rgb.sum().backward()
        return run

    def baseline_fwd_bwd() -> None:
        g = gm.clone().requires_grad_()
        baseline_render(g, cam).sum().backward()

    return {
        "fwd": fwd,
        "fwd_bwd": fwd_bwd("numba"),
        "fisher": lambda: fisher_diag(gm, cam, backend="numba"),
        "baseline_fwd_bwd": baseline_fwd_bwd,
        "baseline_fisher": lambda: baseline_fisher_diag(gm, cam),
        "reference_fwd_bwd": fwd_bwd("torch"),
        "reference_fisher": lambda: fisher_diag(gm, cam, backend="torch"),
    }


def _timings(scene: str | None, n: int, res: int, repeats: int, threads: list[int],
             kinds: list[str]) -> dict[str, Any]:
    """Interleaved rounds of every (kind, thread count): median CPU and wall ms."""
    import torch

    from agilegs.service.nbv.kernels.backend import set_kernel_threads

    def use(kind: str, th: int) -> None:
        kernels = kind in KERNEL_KINDS
        torch.set_num_threads(1 if kernels else th)
        set_kernel_threads(th if kernels else None)

    use("fwd_bwd", threads[0])
    gm, cam = _build(scene, n, res)
    fns = _functions(gm, cam)
    t0 = time.perf_counter()
    fns["fwd_bwd"]()
    first_ms = (time.perf_counter() - t0) * 1e3
    plan = [(k, th) for k in kinds for th in (threads if k in KERNEL_KINDS else threads[:1])]
    for kind, th in plan:  # warm-up
        use(kind, th)
        fns[kind]()
    cpu: dict[tuple[str, int], list[float]] = {p: [] for p in plan}
    wall: dict[tuple[str, int], list[float]] = {p: [] for p in plan}
    for _ in range(repeats):
        for kind, th in plan:
            use(kind, th)
            c0, w0 = time.process_time(), time.perf_counter()
            fns[kind]()
            cpu[(kind, th)].append((time.process_time() - c0) * 1e3)
            wall[(kind, th)].append((time.perf_counter() - w0) * 1e3)
    return {
        "first_call_ms": first_ms,
        "cpu_ms": {f"{k}@{th}": statistics.median(v) for (k, th), v in cpu.items()},
        "wall_ms": {f"{k}@{th}": statistics.median(v) for (k, th), v in wall.items()},
    }


def _peak(scene: str | None, n: int, res: int, kind: str, threads: int) -> dict[str, float]:
    import torch

    from agilegs.service.nbv.kernels.backend import set_kernel_threads

    torch.set_num_threads(1 if kind in KERNEL_KINDS else threads)
    set_kernel_threads(threads)
    gm, cam = _build(scene, n, res)
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    _functions(gm, cam)[kind]()
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {"peak_mb": max(peak - base, 0) / 1024.0}


def _child(q: Any, fn: Callable[..., dict[str, Any]], *args: Any) -> None:
    try:
        q.put(fn(*args))
    except Exception as exc:  # reported to the parent, which logs it
        q.put({"error": repr(exc)})


def _in_child(fn: Callable[..., dict[str, Any]], *args: Any) -> dict[str, Any]:
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    proc = ctx.Process(target=_child, args=(q, fn, *args))
    proc.start()
    out = q.get()
    proc.join()
    return out


def run(args: argparse.Namespace) -> int:
    import torch

    if args.device != "cpu":
        from .render_gpu import run_gpu

        return run_gpu(args)

    sizes = [int(s) for s in str(args.sizes).split(",") if s]
    counts = [int(s) for s in str(args.gaussians).split(",") if s]
    threads = [int(s) for s in str(args.threads).split(",") if s]
    if not sizes or not counts or not threads or min(threads) < 1 or args.repeats < 1:
        raise SystemExit("--sizes, --gaussians, --threads need positive values, --repeats >= 1")
    kinds = list(KERNEL_KINDS) + ([] if args.no_baseline else list(BASELINE_KINDS)) + (
        list(REFERENCE_KINDS) if args.reference else [])
    t1 = threads[0]
    rows = []
    for n in counts:
        for res in sizes:
            out = _in_child(_timings, args.scene, n, res, args.repeats, threads, kinds)
            if "error" in out:
                logger.error("%d Gaussians at %d²: %s", n, res, out["error"])
                return 1
            row: dict[str, Any] = {"gaussians": n, "size": res, **out}
            cpu, wall = out["cpu_ms"], out["wall_ms"]
            for kind in ("fwd_bwd", "fisher"):
                if f"baseline_{kind}@{t1}" in cpu:
                    row[f"ratio_{kind}"] = cpu[f"{kind}@{t1}"] / cpu[f"baseline_{kind}@{t1}"]
                if f"reference_{kind}@{t1}" in cpu:
                    row[f"ratio_reference_{kind}"] = (cpu[f"{kind}@{t1}"]
                                                      / cpu[f"reference_{kind}@{t1}"])
                for th in threads[1:]:
                    row[f"speedup_{kind}@{th}"] = wall[f"{kind}@{t1}"] / wall[f"{kind}@{th}"]
            if args.memory:
                row["peak_mb"] = {}
                for kind in kinds:
                    m = _in_child(_peak, args.scene, n, res, kind, t1)
                    if "error" in m:
                        logger.error("%s at %d² with %d Gaussians: %s", kind, res, n, m["error"])
                        return 1
                    row["peak_mb"][kind] = m["peak_mb"]
            rows.append(row)
    _print(rows, threads, args)
    result = {
        "config": {
            "scene": args.scene,
            "repeats": args.repeats,
            "threads": threads,
            "torch": torch.__version__,
            "device": "cpu",
        },
        "rows": rows,
    }
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(result, fh, indent=2)
    return 0


def _print(rows: list[dict[str, Any]], threads: list[int], args: argparse.Namespace) -> None:
    from rich.console import Console
    from rich.table import Table

    t1 = threads[0]
    table = Table(title=f"agilegs bench render: median of {args.repeats} interleaved rounds, "
                  f"CPU ms on {t1} thread(s); ratios: kernels / baseline")
    cols = ["N", "px", "first call", "fwd", "fwd+bwd", "fisher"]
    if not args.no_baseline:
        cols += ["baseline fwd+bwd", "baseline fisher", "f+b ratio", "fisher ratio"]
    if args.reference:
        cols += ["torch fwd+bwd", "torch fisher"]
    cols += [f"{th} threads f+b / fisher (speed-up)" for th in threads[1:]]
    for c in cols:
        table.add_column(c, justify="right")
    for r in rows:
        cpu = r["cpu_ms"]

        def ms(kind: str, cpu: dict[str, float] = cpu) -> str:
            v = cpu.get(f"{kind}@{t1}")
            return "-" if v is None else f"{v:.1f}"

        cells = [str(r["gaussians"]), f"{r['size']}²", f"{r['first_call_ms']:.0f}", ms("fwd"),
                 ms("fwd_bwd"), ms("fisher")]
        if not args.no_baseline:
            cells += [ms("baseline_fwd_bwd"), ms("baseline_fisher"),
                      f"{r['ratio_fwd_bwd']:.3f}", f"{r['ratio_fisher']:.3f}"]
        if args.reference:
            cells += [ms("reference_fwd_bwd"), ms("reference_fisher")]
        for th in threads[1:]:
            cells.append(f"{r[f'speedup_fwd_bwd@{th}']:.2f}× / {r[f'speedup_fisher@{th}']:.2f}×")
        table.add_row(*cells)
    Console(file=sys.stdout, width=160).print(table)
