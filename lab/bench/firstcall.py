"""``agilegs bench firstcall``: a fresh server's first selection against its tenth.

For each variant, a fresh ``agilegs serve`` (its own state folder, HTTP only, the mapper off):
``warm-up`` (the default server: the kernels compiled in the background at start, the
benchmark waiting for ``/readyz``, as a robot's start-up should) and ``no warm-up``
(``AGILEGS_WARMUP=0``: the first selection compiles what it calls). Each creates a session on
the scene (default: the bundled Spot subsampled to ``--max-gaussians``) with a pool of
``--pool`` candidates, commits three of them, then makes ``--selections`` selections of
``--method`` with commit, timing each at the client (the round trip) and reading the core's
``latency_ms.total``. Reported per variant: the seconds until ready, the first and the tenth
(the last) selection's round trip and their ratio, and the first against the median of the
others (a steadier reference on a shared machine).

``--fresh-cache`` gives the servers an empty numba cache folder (``NUMBA_CACHE_DIR``): a
fresh machine, where the kernels are compiled rather than loaded from the cache.
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from agilegs.lab.scenes import bundled_scene
from agilegs.service.launch import ServerProcess

__all__ = ["add_arguments", "run"]

log = logging.getLogger(__name__)

VARIANTS: tuple[tuple[str, str], ...] = (("warm-up", "1"), ("no warm-up", "0"))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", default=str(bundled_scene("spot")),
                        help="a .splat / .ply scene (default: the bundled Spot)")
    parser.add_argument("--max-gaussians", type=int, default=3000,
                        help="the scene subsampled to this many Gaussians (default 3000)")
    parser.add_argument("--pool", type=int, default=60, help="candidates (default 60)")
    parser.add_argument("--size", type=int, default=64, help="image side in pixels (64)")
    parser.add_argument("--method", default="agile_plus", help="the method (agile_plus)")
    parser.add_argument("--selections", type=int, default=10,
                        help="selections per server; the last is compared with the first (10)")
    parser.add_argument("--variants", default="warm-up,no warm-up",
                        help="which servers: 'warm-up', 'no warm-up' or both (default)")
    parser.add_argument("--fresh-cache", action="store_true",
                        help="an empty numba cache for the servers (a fresh machine)")
    parser.add_argument("--json", metavar="PATH", help="write the results as JSON")


def _session(client: Any, args: argparse.Namespace, sid: str) -> None:
    import numpy as np

    from agilegs.service.nbv import load_scene
    from agilegs.service.nbv.candidates import capture_pool, scene_center_radius

    g = load_scene(args.scene, max_gaussians=args.max_gaussians, seed=0)
    center, r98 = scene_center_radius(g.means)
    pool = capture_pool(center, 2.6 * r98, args.pool, seed=0).double().numpy()
    f = args.size / 2 / np.tan(np.radians(25))
    intr = {"fx": f, "fy": f, "cx": args.size / 2, "cy": args.size / 2,
            "width": args.size, "height": args.size}
    client.create_session(intr, id=sid, gaussians={k: v.numpy() for k, v in g.items()},
                          pool=pool)
    for cid in (0, args.pool // 3, 2 * args.pool // 3):
        client.commit(sid, cid)


def _one(name: str, warmup: str, args: argparse.Namespace, root: Path,
         env: dict[str, str]) -> dict[str, Any]:
    from agilegs.client import Client

    t0 = time.perf_counter()
    server = ServerProcess(root / name.replace(" ", "-") / "state", zenoh=False,
                           env={"AGILEGS_WARMUP": warmup, "AGILEGS_MAPPER": "0", **env},
                           args=["--log-level", "warning"])
    server.start(timeout=120.0)
    try:
        ready_s = server.wait_ready(timeout=1800.0) + (time.perf_counter() - t0)
        with Client(server.url, timeout=1800.0) as c:
            _session(c, args, "firstcall")
            rounds, cores, stages = [], [], []
            for _ in range(args.selections):
                t = time.perf_counter()
                d = c.select("firstcall", method=args.method, commit=True)
                rounds.append((time.perf_counter() - t) * 1e3)
                cores.append(float(d.latency_ms.get("total", float("nan"))))
                stages.append(dict(d.latency_ms))
    finally:
        server.stop()
    rest = statistics.median(rounds[1:])
    return {"variant": name, "ready_s": ready_s, "round_trip_ms": rounds, "core_ms": cores,
            "latency_ms": stages, "first_ms": rounds[0], "last_ms": rounds[-1],
            "ratio": rounds[0] / rounds[-1], "rest_median_ms": rest,
            "ratio_median": rounds[0] / rest}


def run(args: argparse.Namespace) -> int:
    logging.getLogger("httpx").setLevel(logging.WARNING)
    if args.selections < 2 or args.pool < args.selections + 3:
        sys.stderr.write("agilegs bench firstcall: --selections must be >= 2 and --pool hold "
                         "them and three commits\n")
        return 2
    chosen = [v.strip() for v in args.variants.split(",") if v.strip()]
    unknown = set(chosen) - {n for n, _ in VARIANTS}
    if unknown or not chosen:
        sys.stderr.write(f"agilegs bench firstcall: --variants: unknown {sorted(unknown)}\n")
        return 2
    results = []
    with tempfile.TemporaryDirectory(prefix="agilegs-firstcall-") as tmp:
        root = Path(tmp)
        for name, warmup in VARIANTS:
            if name not in chosen:
                continue
            env = {}
            if args.fresh_cache:
                (root / f"numba-{warmup}").mkdir()
                env["NUMBA_CACHE_DIR"] = str(root / f"numba-{warmup}")
            log.info("fresh server, %s", name)
            results.append(_one(name, warmup, args, root, env))
    n = args.selections
    lines = [f"{args.method}, {args.max_gaussians} Gaussians, pool {args.pool}, "
             f"{args.size}x{args.size}, {'empty' if args.fresh_cache else 'existing'} numba "
             "cache", "",
             f"| server | ready (s) | 1st selection (ms) | {n}th (ms) | 1st / {n}th | median of "
             f"2nd-{n}th (ms) | 1st / median |", "|---|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        lines.append(f"| {r['variant']} | {r['ready_s']:.1f} | {r['first_ms']:.0f} | "
                     f"{r['last_ms']:.0f} | {r['ratio']:.2f} | {r['rest_median_ms']:.0f} | "
                     f"{r['ratio_median']:.2f} |")
    sys.stdout.write("\n".join(lines) + "\n")
    if args.json:
        Path(args.json).write_text(json.dumps({"args": {k: v for k, v in vars(args).items()
                                                        if not k.startswith("_")},
                                               "results": results}, indent=2, default=str))
    return 0
